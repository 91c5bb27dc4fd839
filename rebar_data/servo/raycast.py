"""Exact ray casts against the rebar mesh (Open3D's RaycastingScene): visibility tests and depth images."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from rebar_data.geometry.build import RebarMesh


class Raycaster:
    """Built once per mesh; casts batches of rays and reports hit distance, part id and surface normal."""

    def __init__(self, rm: RebarMesh) -> None:
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(np.asarray(rm.mesh.vertices, np.float32)),
            o3d.core.Tensor(np.asarray(rm.mesh.faces, np.uint32)),
        )
        self._part_of_triangle = np.asarray(rm.triangle_part_id, np.int32)

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Hit distance (inf on a miss), part id (-1 on a miss) and unit normal per ray."""
        rays = np.hstack([np.atleast_2d(origins), np.atleast_2d(dirs)]).astype(np.float32)
        hit = self._scene.cast_rays(o3d.core.Tensor(rays))
        t = hit["t_hit"].numpy().astype(np.float64)
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        hit_any = np.isfinite(t)
        part = np.full(len(t), -1, np.int32)
        part[hit_any] = self._part_of_triangle[prim[hit_any]]
        return t, part, hit["primitive_normals"].numpy().astype(np.float64)

    def cast_t_normal(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hit distance (float32, inf on a miss) and normal of rays (N, 6) float32: origin then unit direction."""
        hit = self._scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        return hit["t_hit"].numpy(), hit["primitive_normals"].numpy()

    def cast_rays(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(t_hit, instance)``: the renderer's ray-cast signature, for the label rules."""
        t, part, _ = self.cast(origins, dirs)
        return t, part
