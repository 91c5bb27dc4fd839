"""Exact depth and instance ids by ray cast, shared by every renderer so labels never depend on the engine.

:class:`Raycaster` is the package's one ray caster: an ``open3d.t.geometry.RaycastingScene`` of a rebar mesh
and, optionally, the scene's objects, giving each ray's first hit (distance, instance id, surface normal).
The labels' visibility rays, the dataset's depth and instance images and the servo loop's ray-cast frames
all go through it.

:class:`SceneRaycast` is the renderers' part of it: one ray through every pixel centre for metric depth
(camera-frame z) and instance ids, and the world rays the labelling code casts for visibility. The Open3D
renderer and the Cycles renderer both use it: whichever engine draws the RGB image, depth, instance maps and
labels are the same.

Instance ids: ``>= 0`` the part of ``rm.parts`` (primitive ids of the merged mesh mapped through
``rm.triangle_part_id``), ``-1`` nothing, and the objects' own ids for the surroundings (``-2`` ground,
``-3`` distractors).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rebar_data.camera import Intrinsics
from rebar_data.geometry.build import RebarMesh
from rebar_data.render.sensor import apply_sensor
from rebar_data.scene.sample import SensorSample
from rebar_data.scene.surroundings import SceneObject
from rebar_data.timing import StageTimer

NOTHING_ID = -1


@dataclass
class Frame:
    """What a renderer gives for one camera pose, whichever engine drew the image."""

    rgb: np.ndarray  # (H, W, 3) uint8, after sensor effects
    depth_m: np.ndarray  # (H, W) float32, metric z in the camera frame, 0 where nothing was hit
    instance: np.ndarray  # (H, W) int32: >= 0 part id; -1 nothing; -2 ground; -3 distractors


class Raycaster:
    """First hits of rays against a rebar mesh and the scene's ``objects``, built once per scene."""

    def __init__(self, rm: RebarMesh, objects: Sequence[SceneObject] = ()):
        import open3d as o3d

        self._o3d = o3d
        self._rm = rm
        rs = o3d.t.geometry.RaycastingScene()
        rs.add_triangles(
            o3d.core.Tensor(np.asarray(rm.mesh.vertices, np.float32)),
            o3d.core.Tensor(np.asarray(rm.mesh.faces, np.uint32)),
        )
        ids = [0]  # the rebar's ids come from its triangles
        for obj in objects:
            rs.add_triangles(
                o3d.core.Tensor(obj.shape.vertices.astype(np.float32)),
                o3d.core.Tensor(obj.shape.triangles.astype(np.uint32)),
            )
            ids.append(obj.instance_id)
        self._scene = rs
        # instance id of each ray-cast geometry (0: the rebar), then the id of a miss
        self._geom_lut = np.array([*ids, NOTHING_ID], np.int32)

    def cast_rays(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit of each world ray against everything in the scene: distance in metres along the
        (normalised) direction, ``inf`` when nothing is hit, and the instance id there."""
        d = np.asarray(directions, np.float64)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        rays = np.empty((len(d), 6), np.float32)
        rays[:, :3] = np.asarray(origins, np.float64)
        rays[:, 3:] = d
        t, inst = self.cast(rays)
        return t.astype(np.float64), inst

    def cast(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hit distances (in ray-direction lengths, inf = miss) and instance ids of (N, 6) float32 rays
        (origin, then direction)."""
        hit = self._scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays))
        t = hit["t_hit"].numpy()
        geom = hit["geometry_ids"].numpy()  # uint32; Open3D marks a miss with the largest value
        # one look-up for every geometry (a miss reads the extra last entry), then the rebar's hits get
        # their part's id from the triangle they hit
        inst = self._geom_lut[np.minimum(geom, len(self._geom_lut) - 1)]
        rebar = geom == 0
        inst[rebar] = self._rm.triangle_part_id[hit["primitive_ids"].numpy()[rebar]]
        return t, inst

    def cast_t_normal(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hit distance (float32, inf on a miss) and the hit triangle's unit normal of (N, 6) float32 rays
        (origin, then direction)."""
        hit = self._scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays))
        return hit["t_hit"].numpy(), hit["primitive_normals"].numpy()


class SceneRaycast:
    """Ray casts against the rebar and the scene's objects; a renderer mixes it in.

    The renderer calls :meth:`_init_raycast` once, keeps its mesh in ``self._rm`` and calls
    :meth:`_build_raycast` with the scene's objects in ``set_scene``; its ``render`` draws the linear image
    and hands it to :meth:`_finish_frame`.
    """

    _rm: RebarMesh | None
    intrinsics: Intrinsics
    timer: StageTimer  # seconds per stage of render(): the engine's own, rays, sensor

    def _init_raycast(self, intrinsics: Intrinsics) -> None:
        self._raycast: Raycaster | None = None
        # (x, y) of the ray (x, y, 1) through every pixel centre, (H*W, 2)
        self._pixel_xy = np.ascontiguousarray(intrinsics.pixel_rays()[:, :2], np.float32)
        self._rays = np.empty((len(self._pixel_xy), 6), np.float32)

    def _build_raycast(self, objects: list[SceneObject]) -> None:
        self._raycast = Raycaster(self._rm, objects)

    def cast_rays(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`Raycaster.cast_rays` against the current scene."""
        if self._raycast is None:
            raise RuntimeError("set_mesh(rm) and set_scene(scene) must come before cast_rays")
        return self._raycast.cast_rays(origins, directions)

    def depth_and_instance(self, world_from_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact depth (z, metres, 0 = nothing) and instance ids of every pixel, by ray cast."""
        k = self.intrinsics
        T = np.asarray(world_from_camera, float)
        R = T[:3, :3].astype(np.float32)
        rays = self._rays  # reused every frame
        rays[:, :3] = T[:3, 3]
        # direction = R @ (x, y, 1), written out: a (N, 3) @ (3, 3) matmul is several times slower
        np.multiply(self._pixel_xy[:, :1], R[:, 0], out=rays[:, 3:])
        rays[:, 3:] += self._pixel_xy[:, 1:] * R[:, 1]
        rays[:, 3:] += R[:, 2]
        depth, inst = self._raycast.cast(rays)  # directions have camera z = 1, so t is z
        depth[np.isinf(depth)] = 0.0
        return depth.reshape(k.height, k.width), inst.reshape(k.height, k.width)

    def _finish_frame(
        self, raw: np.ndarray, world_from_camera: np.ndarray, sensor: SensorSample, rng: np.random.Generator
    ) -> Frame:
        """The frame of a rendered linear image ``raw``: depth and instance ids by ray cast, then the
        ``sensor``'s effects (noise from ``rng``)."""
        with self.timer("rays"):
            depth, inst = self.depth_and_instance(world_from_camera)
        k = self.intrinsics
        with self.timer("sensor"):
            rgb = apply_sensor(raw, sensor, rng, principal_point=(k.cx, k.cy))
        return Frame(rgb, depth, inst)
