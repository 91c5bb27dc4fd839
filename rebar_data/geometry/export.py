"""Writes a rebar mesh to disk: GLB (one node per part), PLY (merged, with part and bar id per face),
bars.parquet and crossings.parquet. Outputs are byte-identical for the same config and seed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import trimesh

from rebar_data.geometry.build import RebarMesh

BAR_COLOR = (150, 95, 60, 255)
WIRE_COLOR = (120, 120, 125, 255)


def bars_table(rm: RebarMesh) -> pa.Table:
    rows: dict[str, list] = {
        k: [] for k in ("bar_id", "kind", "direction", "layer", "diameter_m", "length_m")
    }
    geo: dict[str, list] = {
        k: []
        for k in (
            "start_x",
            "start_y",
            "start_z",
            "end_x",
            "end_y",
            "end_z",
            "center_x",
            "center_y",
            "center_z",
        )
    }
    extra: dict[str, list] = {k: [] for k in ("radius_m", "axis", "e1", "sweep_rad")}
    for b in rm.bars:
        c = b.curve
        rows["bar_id"].append(b.bar_id)
        rows["kind"].append(c.kind)
        rows["direction"].append(b.direction)
        rows["layer"].append(b.layer)
        rows["diameter_m"].append(b.diameter_m)
        rows["length_m"].append(c.length)
        for name, v in (("start", c.start), ("end", c.end)):
            for ax, x in zip("xyz", v, strict=True):
                geo[f"{name}_{ax}"].append(float(x))
        arc = c.kind == "arc"
        for ax, x in zip("xyz", c.center if arc else (np.nan,) * 3, strict=True):
            geo[f"center_{ax}"].append(float(x))
        extra["radius_m"].append(float(c.radius) if arc else np.nan)
        extra["axis"].append([float(x) for x in c.axis] if arc else None)
        extra["e1"].append([float(x) for x in c.e1] if arc else None)
        extra["sweep_rad"].append(float(c.sweep) if arc else np.nan)
    cols = {**rows, **geo, **extra}
    schema = pa.schema(
        [
            ("bar_id", pa.int32()),
            ("kind", pa.string()),
            ("direction", pa.int8()),
            ("layer", pa.int16()),
            ("diameter_m", pa.float64()),
            ("length_m", pa.float64()),
            *[(k, pa.float64()) for k in geo],
            ("radius_m", pa.float64()),
            ("axis", pa.list_(pa.float64(), 3)),
            ("e1", pa.list_(pa.float64(), 3)),
            ("sweep_rad", pa.float64()),
        ]
    )
    table = pa.table(cols, schema=schema)
    src = rm.layout.ifc
    if src is not None:  # read from IFC: where each piece comes from
        table = table.append_column("piece", pa.array(src.piece, pa.int16()))
        table = table.append_column("global_id", pa.array(src.global_id, pa.string()))
        table = table.append_column("ifc_class", pa.array(src.ifc_class, pa.string()))
        table = table.append_column("face", pa.array(rm.layout.faces.piece_face.astype(np.int16)))
    return table


def crossings_table(rm: RebarMesh) -> pa.Table:
    c = rm.crossings
    n = len(c)
    tied = np.zeros(n, bool)
    tied[rm.part_crossing_id[rm.part_crossing_id >= 0]] = True
    cols = {
        "crossing_id": pa.array(np.arange(n, dtype=np.int32)),
        "bar_a": pa.array(c.bar_a),
        "bar_b": pa.array(c.bar_b),
        "layer": pa.array(c.layer.astype(np.int16)),
        "x": pa.array(c.point[:, 0]),
        "y": pa.array(c.point[:, 1]),
        "z": pa.array(c.point[:, 2]),
        "normal_x": pa.array(c.normal[:, 0]),
        "normal_y": pa.array(c.normal[:, 1]),
        "normal_z": pa.array(c.normal[:, 2]),
        "gap_m": pa.array(c.gap_m),
        "tie_wire": pa.array(tied),
    }
    for name, pts in (("a", c.point_a), ("b", c.point_b)):
        for k, ax in enumerate("xyz"):
            cols[f"{ax}_{name}"] = pa.array(pts[:, k])
    src = rm.layout.ifc
    if src is not None:  # read from IFC: the two bars' GlobalIds
        gid = np.array(src.global_id, dtype=object)
        cols["global_id_a"] = pa.array(gid[c.piece_a].tolist() if n else [], pa.string())
        cols["global_id_b"] = pa.array(gid[c.piece_b].tolist() if n else [], pa.string())
    return pa.table(cols)


def write_parquet(table: pa.Table, path: Path) -> None:
    """Parquet with fixed settings and no wall-clock metadata, so identical tables give identical bytes."""
    pq.write_table(table, path, compression="zstd", write_statistics=True, store_schema=True)


def _glb_scene(rm: RebarMesh) -> trimesh.Scene:
    scene = trimesh.Scene()
    for p in rm.parts:
        mesh = p.mesh.copy()
        color = BAR_COLOR if p.kind == "bar" else WIRE_COLOR
        mesh.visual = trimesh.visual.ColorVisuals(mesh, face_colors=np.tile(color, (len(mesh.faces), 1)))
        name = f"bar_{p.bar_id:04d}" if p.kind == "bar" else f"tie_wire_{p.crossing_id:05d}"
        scene.add_geometry(mesh, node_name=name, geom_name=name)
    return scene


def write_mesh_outputs(rm: RebarMesh, out: Path) -> None:
    """Write every output into ``out`` (created if missing)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "mesh.glb").write_bytes(_glb_scene(rm).export(file_type="glb"))
    merged = rm.mesh.copy()
    merged.face_attributes = {
        "part_id": rm.triangle_part_id.astype(np.int32),
        "bar_id": rm.triangle_bar_id.astype(np.int32),
    }
    (out / "mesh.ply").write_bytes(
        trimesh.exchange.ply.export_ply(merged, encoding="binary", include_attributes=True)
    )
    write_parquet(bars_table(rm), out / "bars.parquet")
    write_parquet(crossings_table(rm), out / "crossings.parquet")
    summary = {
        "bars": len(rm.bars),
        "crossings": len(rm.crossings),
        "tie_wires": int(sum(p.kind == "tie_wire" for p in rm.parts)),
        "triangles": int(len(rm.mesh.faces)),
        "watertight": bool(rm.mesh.is_watertight),
        "seed": rm.config.seed,
        "config": rm.config.model_dump(mode="json"),
    }
    src = rm.layout.ifc
    if src is not None:  # read from IFC: bars are counted whole; the pieces, the file and what was left out
        summary["bars"] = len({b.bar_id for b in rm.bars})
        summary["centerline_pieces"] = len(rm.bars)
        summary["ifc"] = {
            "path": src.path,
            "sha256": src.sha256,
            "schema": src.schema,
            "elements": src.elements,
            "skipped": src.skipped,
            "dropped": src.dropped,
        }
        summary["surface"] = rm.layout.surface.record()
        summary["faces"] = rm.layout.faces.record()
    (out / "mesh.json").write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
