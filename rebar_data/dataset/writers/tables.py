"""Parquet tables: ``samples`` (one row per image) and ``keypoints`` (one row per crossing per image)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa

from rebar_data.dataset import layout
from rebar_data.dataset.plan import Plan
from rebar_data.dataset.worker import FrameRecord
from rebar_data.geometry.build import RebarMesh
from rebar_data.geometry.export import write_parquet


def samples_table(
    plan: Plan, records: dict[str, FrameRecord], intrinsics, *, depth: bool, instances: bool
) -> pa.Table:
    traj = {t.trajectory_id: t for t in plan.trajectories}
    rows: dict[str, list] = {}

    def put(key: str, value) -> None:
        rows.setdefault(key, []).append(value)

    for s in sorted(plan.samples, key=lambda s: s.image_id):
        rec = records[s.image_id]
        vis = rec.labels.visibility
        put("image_id", s.image_id)
        put("split", s.split)
        put("file_name", layout.image_path(s.split, s.image_id))
        put("width", intrinsics.width)
        put("height", intrinsics.height)
        put("fx", float(intrinsics.fx))
        put("fy", float(intrinsics.fy))
        put("cx", float(intrinsics.cx))
        put("cy", float(intrinsics.cy))
        put("world_from_camera", [float(x) for x in np.asarray(s.world_from_camera, float).reshape(-1)])
        put("scene_id", s.scene_id)
        put("trajectory_id", s.trajectory_id)
        put("trajectory_kind", traj[s.trajectory_id].kind)
        put("frame", s.frame)
        put("sample_index", s.index)
        put("image_sha256", rec.image_sha256)
        put("depth_file", layout.depth_path(s.split, s.image_id) if depth else None)
        put("sensor_depth_file", layout.sensor_depth_path(s.split, s.image_id) if depth else None)
        put("instance_file", layout.instance_path(s.split, s.image_id) if instances else None)
        put("n_visible", int((vis == 2).sum()))
        put("n_occluded", int((vis == 1).sum()))
        for k, v in sorted(plan.scenes[traj[s.trajectory_id].scene_index].record().items()):
            put(k, v)
        for k, v in sorted(rec.sensor.items()):
            put(k, v)
    fixed = {
        "width": pa.int32(),
        "height": pa.int32(),
        "world_from_camera": pa.list_(pa.float64(), 16),
        "frame": pa.int32(),
        "sample_index": pa.int32(),
        "n_visible": pa.int32(),
        "n_occluded": pa.int32(),
        "depth_file": pa.string(),
        "sensor_depth_file": pa.string(),
        "instance_file": pa.string(),
    }
    return pa.table({k: pa.array(v, type=fixed.get(k)) for k, v in rows.items()})


def keypoints_table(plan: Plan, records: dict[str, FrameRecord], rm: RebarMesh) -> pa.Table:
    c = rm.crossings
    n = len(c)
    tied = np.zeros(n, bool)
    tied[rm.part_crossing_id[rm.part_crossing_id >= 0]] = True
    order = sorted(plan.samples, key=lambda s: s.image_id)
    cols: dict[str, list[np.ndarray]] = {}

    def put(key: str, value: np.ndarray) -> None:
        cols.setdefault(key, []).append(value)

    for s in order:
        lab = records[s.image_id].labels
        put("image_id", np.full(n, s.image_id, dtype=object))
        put("split", np.full(n, s.split, dtype=object))
        put("crossing_id", np.arange(n, dtype=np.int32))
        put("bar_a", c.bar_a.astype(np.int32))
        put("bar_b", c.bar_b.astype(np.int32))
        put("layer", c.layer.astype(np.int16))
        put("u", lab.u.astype(np.float64))
        put("v", lab.v.astype(np.float64))
        put("visibility", lab.visibility.astype(np.int8))
        put("x_world", lab.point_world[:, 0].astype(np.float64))
        put("y_world", lab.point_world[:, 1].astype(np.float64))
        put("z_world", lab.point_world[:, 2].astype(np.float64))
        put("depth_m", lab.depth_m.astype(np.float64))
        put("box_size_px", lab.box_size_px.astype(np.float64))
        put("tie_wire", tied)
        put("hit_instance", lab.hit_instance.astype(np.int32))
        put("x_crossing", c.point[:, 0])
        put("y_crossing", c.point[:, 1])
        put("z_crossing", c.point[:, 2])
    return pa.table({k: pa.array(np.concatenate(v)) for k, v in cols.items()})


def write_tables(out: Path, samples: pa.Table, keypoints: pa.Table) -> None:
    (out / "tables").mkdir(parents=True, exist_ok=True)
    write_parquet(samples, out / layout.SAMPLES)
    write_parquet(keypoints, out / layout.KEYPOINTS)
