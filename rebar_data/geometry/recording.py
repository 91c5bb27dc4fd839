"""A Rerun recording of a rebar mesh and its crossings, for review in the viewer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from rebar_data.geometry.build import RebarMesh


def write_mesh_recording(rm: RebarMesh, path: Path) -> None:
    rec = rr.RecordingStream("rebar_mesh")
    rec.save(str(path), default_blueprint=rrb.Spatial3DView(origin="world", name="rebar mesh"))
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    bar_tri = rm.triangle_bar_id
    colors = np.where((bar_tri >= 0)[:, None], [150, 95, 60], [170, 170, 175]).astype(np.uint8)
    # Rerun colours vertices; repeat vertices per triangle so each face keeps its own colour.
    faces = np.asarray(rm.mesh.faces)
    verts = np.asarray(rm.mesh.vertices, np.float32)[faces.reshape(-1)]
    rec.log(
        "world/mesh",
        rr.Mesh3D(
            vertex_positions=verts,
            triangle_indices=np.arange(len(verts), dtype=np.uint32).reshape(-1, 3),
            vertex_colors=np.repeat(colors, 3, axis=0),
        ),
        static=True,
    )
    c = rm.crossings
    labels = [
        f"crossing {i}: bars {a}/{b}, gap {g * 1000:.2f} mm"
        for i, (a, b, g) in enumerate(zip(c.bar_a, c.bar_b, c.gap_m, strict=True))
    ]
    rec.log(
        "world/crossings", rr.Points3D(c.point, radii=0.008, colors=[255, 40, 40], labels=labels), static=True
    )
    rec.log(
        "world/crossings/normals",
        rr.Arrows3D(origins=c.point, vectors=c.normal * 0.05, colors=[60, 160, 255]),
        static=True,
    )
    rec.flush()
