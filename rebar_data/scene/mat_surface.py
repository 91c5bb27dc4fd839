"""The mat as a smooth surface with 2D coordinates, for placing cameras, lights and surroundings.

The surface passes through the crossings: a plane for planar meshes, a cylinder about the tunnel axis
for tunnel segments, and for a mesh read from IFC the plane or cylinder fitted to its bars
(:mod:`rebar_data.geometry.surface_fit`), in the fit's frame. Coordinates ``(a, b)`` are metres along the
frame's x axis and along its y direction (arc length on a cylinder), so a trajectory can walk across a
curved mat at a constant stand-off. Heights are measured along the outward normal (for IFC, the camera-side
normal), positive on the camera's side.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rebar_data.geometry.build import RebarMesh
from rebar_data.geometry.crossings import Crossings
from rebar_data.geometry.specs import MeshLayout


@dataclass(frozen=True)
class MatSurface:
    """Plane or cylinder through the crossings of a rebar mesh, in world coordinates."""

    kind: str  # "planar" | "tunnel_segment"
    world_from_mesh: np.ndarray  # 4x4
    origin_mesh: np.ndarray  # planar: a point of the plane; tunnel: a point of the axis (mesh frame)
    radius_m: float  # tunnel: the surface's radius; planar: 0
    crossing_ab: np.ndarray  # (N, 2)
    height_range_m: tuple[float, float]  # lowest and highest mesh point above the surface
    side: int = 1  # a cylinder seen from inside (a fitted surface's camera side): -1

    @staticmethod
    def of(rm: RebarMesh) -> MatSurface:
        """The surface through ``rm``'s crossings (or its bars' points when it has none)."""
        vertices = np.asarray(rm.mesh.vertices)
        if len(rm.crossings):
            surf = MatSurface.of_crossings(rm.layout, rm.crossings)
        else:
            surf = MatSurface.through(rm.layout, vertices)
        h = surf.height(vertices)
        return replace(surf, height_range_m=(float(h.min()), float(h.max())))

    @staticmethod
    def of_crossings(layout: MeshLayout, crossings: Crossings) -> MatSurface:
        """The surface through the crossings; for a mesh read from IFC, through its top mat's crossings when
        it keeps any (with ``crossings: all`` the others lie in other mats)."""
        points = crossings.point
        if layout.surface is not None and np.any(crossings.layer == layout.surface.top_mat):
            points = points[crossings.layer == layout.surface.top_mat]
        return MatSurface.through(layout, points)

    @staticmethod
    def through(layout: MeshLayout, points: np.ndarray) -> MatSurface:
        """The surface of ``layout``'s kind and pose through ``points`` (world; the crossings), without the
        solid mesh: its height range is left at zero."""
        fit = layout.surface
        if fit is not None:
            T = fit.world_from_surface
            local = (points - T[:3, 3]) @ T[:3, :3]
            if fit.kind == "cylinder":
                radius = float(np.mean(np.linalg.norm(local[:, 1:], axis=1)))
                surf = MatSurface(
                    "tunnel_segment", T, np.zeros(3), radius, np.zeros((0, 2)), (0.0, 0.0), fit.side
                )
            else:
                origin = np.array([0.0, 0.0, float(np.mean(local[:, 2]))])
                surf = MatSurface("planar", T, origin, 0.0, np.zeros((0, 2)), (0.0, 0.0))
            return replace(surf, crossing_ab=surf.to_ab(points))
        T = layout.world_from_mesh
        local = (points - T[:3, 3]) @ T[:3, :3]
        if layout.kind == "tunnel_segment":
            axis_point = np.asarray(layout.axis_point, float)
            radial = local[:, 1:] - axis_point[1:]
            radius = float(np.mean(np.linalg.norm(radial, axis=1)))
            origin = axis_point
        else:
            origin = np.array([0.0, 0.0, float(np.mean(local[:, 2]))])
            radius = 0.0
        surf = MatSurface(layout.kind, T, origin, radius, np.zeros((0, 2)), (0.0, 0.0))
        return replace(surf, crossing_ab=surf.to_ab(points))

    @property
    def is_tunnel(self) -> bool:
        return self.kind == "tunnel_segment"

    def _to_local(self, points: np.ndarray) -> np.ndarray:
        T = self.world_from_mesh
        return (np.atleast_2d(points) - T[:3, 3]) @ T[:3, :3] - self.origin_mesh

    def _to_world(self, local: np.ndarray, *, direction: bool = False) -> np.ndarray:
        T = self.world_from_mesh
        if direction:
            return local @ T[:3, :3].T
        return (local + self.origin_mesh) @ T[:3, :3].T + T[:3, 3]

    def to_ab(self, points: np.ndarray) -> np.ndarray:
        """Surface coordinates (N, 2) of world points (their foot on the surface)."""
        local = self._to_local(points)
        if self.is_tunnel:
            return np.stack([local[:, 0], self.radius_m * np.arctan2(local[:, 1], local[:, 2])], axis=1)
        return local[:, :2].copy()

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (N,) of world points above the surface, along the outward normal."""
        local = self._to_local(points)
        if self.is_tunnel:
            return self.side * (np.linalg.norm(local[:, 1:], axis=1) - self.radius_m)
        return local[:, 2]

    def frame(self, ab: np.ndarray, height_m: float | np.ndarray = 0.0) -> tuple[np.ndarray, ...]:
        """Points at ``height_m`` above the surface at ``ab`` (N, 2), with the unit tangents along a and b and
        the outward normal there: four (N, 3) arrays."""
        ab = np.atleast_2d(np.asarray(ab, float))
        h = np.broadcast_to(np.asarray(height_m, float), (len(ab),))
        if self.is_tunnel:
            psi = ab[:, 1] / self.radius_m
            normal = np.stack([np.zeros_like(psi), np.sin(psi), np.cos(psi)], axis=1)
            t_b = np.stack([np.zeros_like(psi), np.cos(psi), -np.sin(psi)], axis=1)
            local = np.stack([ab[:, 0], np.zeros_like(psi), np.zeros_like(psi)], axis=1)
            local = local + (self.radius_m + self.side * h)[:, None] * normal
            normal = self.side * normal
        else:
            normal = np.tile([0.0, 0.0, 1.0], (len(ab), 1))
            t_b = np.tile([0.0, 1.0, 0.0], (len(ab), 1))
            local = np.concatenate([ab, h[:, None]], axis=1)
        t_a = np.tile([1.0, 0.0, 0.0], (len(ab), 1))
        return (
            self._to_world(local),
            self._to_world(t_a, direction=True),
            self._to_world(t_b, direction=True),
            self._to_world(normal, direction=True),
        )

    def bounds(self, margin_m: float = 0.0) -> np.ndarray:
        """``[[a_min, b_min], [a_max, b_max]]`` of the crossings, shrunk by ``margin_m`` (never past the middle)."""
        lo, hi = self.crossing_ab.min(0), self.crossing_ab.max(0)
        mid = (lo + hi) / 2.0
        return np.stack([np.minimum(lo + margin_m, mid), np.maximum(hi - margin_m, mid)])

    def centre(self) -> np.ndarray:
        """Surface coordinates of the middle of the crossings' extent."""
        return self.bounds().mean(0)
