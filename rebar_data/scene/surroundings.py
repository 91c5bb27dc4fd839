"""Geometry of a scene's surroundings and distractors, built around the mat from a SceneSample.

- ground: a large plane beneath the mat's lowest point (tilted a little), or a surface that follows the
  mat's curvature (the segment's mould) with the plane further out;
- lower layer: a second bar mat ``lower_layer_depth_m`` inside the element, shifted in its plane;
- spacers: short concrete blocks on the ground beneath crossings (holding the mat where it is close);
- loose tie wire: short bent wires lying on the ground;
- formwork edges: plywood boards along the chosen sides of the mat.

Ground objects get instance id -2 and distractors -3 (the renderer's convention). Everything random
comes from the sample's distractor seed, so the same sample gives the same geometry.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rebar_data.geometry.build import RebarMesh
from rebar_data.scene.mat_surface import MatSurface
from rebar_data.scene.sample import SceneSample
from rebar_data.scene.shapes import Shape, cylinder, grid, polyline_tube

GROUND_ID = -2
DISTRACTOR_ID = -3


@dataclass(frozen=True)
class SceneObject:
    """One renderable, ray-castable piece of the surroundings."""

    name: str
    shape: Shape
    material: str  # "ground" | "rebar" | "concrete" | "plywood" | "tie_wire"
    instance_id: int
    cast_shadows: bool = True


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _plane(centre: np.ndarray, t_a: np.ndarray, t_b: np.ndarray, size: float) -> Shape:
    s = np.array([-size / 2.0, size / 2.0])
    pts = centre + s[:, None, None] * t_a + s[None, :, None] * t_b
    uv = np.stack(np.meshgrid(s, s, indexing="ij"), axis=-1)
    flip = np.dot(np.cross(t_a, t_b), np.cross(pts[1, 0] - pts[0, 0], pts[0, 1] - pts[0, 0])) < 0
    return grid(pts, uv, flip=bool(flip))


def _ground(scene: SceneSample, surf: MatSurface, rm: RebarMesh) -> list[SceneObject]:
    g = scene.ground
    centre, t_a, t_b, n = (x[0] for x in surf.frame(surf.centre()))
    verts = np.asarray(rm.mesh.vertices)
    objects = []
    keep_below = verts  # the plane stays at least distance_m beneath these points
    tilt = 0.0 if g.shape == "follow" else np.radians(g.tilt_deg)  # a planar mat's mould is parallel to it
    if g.shape == "follow" and surf.is_tunnel:
        h = surf.height_range_m[0] - g.distance_m
        lo, hi = surf.bounds()
        a = np.linspace(lo[0] - 1.5, hi[0] + 1.5, 2)
        b = np.linspace(lo[1] - 1.0, hi[1] + 1.0, 48)
        ab = np.stack(np.meshgrid(a, b, indexing="ij"), axis=-1).reshape(-1, 2)
        pts = surf.frame(ab, h)[0].reshape(len(a), len(b), 3)
        uv = ab.reshape(len(a), len(b), 2) * np.array([1.0, (surf.radius_m + surf.side * h) / surf.radius_m])
        objects.append(SceneObject("ground_mould", grid(pts, uv), "ground", GROUND_ID))
        keep_below = np.concatenate([verts, pts.reshape(-1, 3) - 0.3 * n])
    tilt_axis = np.cos(np.radians(g.tilt_azimuth_deg)) * t_a + np.sin(np.radians(g.tilt_azimuth_deg)) * t_b
    R = _rotation(tilt_axis, tilt)
    m = R @ n
    drop = float(np.min((keep_below - centre) @ m)) - g.distance_m
    objects.append(
        SceneObject(
            "ground_plane", _plane(centre + drop * m, R @ t_a, R @ t_b, g.size_m), "ground", GROUND_ID
        )
    )
    return objects


class _GroundProbe:
    """Ray casts against the ground objects only (to stand things on the ground)."""

    def __init__(self, ground: list[SceneObject]):
        import open3d as o3d

        self._o3d = o3d
        self._rs = o3d.t.geometry.RaycastingScene()
        for obj in ground:
            self._rs.add_triangles(
                o3d.core.Tensor(obj.shape.vertices.astype(np.float32)),
                o3d.core.Tensor(obj.shape.triangles.astype(np.uint32)),
            )

    def __call__(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance along each ray to the ground (inf when missed) and the hit normals."""
        rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
        hit = self._rs.cast_rays(self._o3d.core.Tensor(rays))
        return hit["t_hit"].numpy().astype(float), hit["primitive_normals"].numpy().astype(float)


def _lower_layer(scene: SceneSample, surf: MatSurface, rm: RebarMesh) -> list[SceneObject]:
    """A copy of the mat's bars (a mesh read from IFC: its top mat's), moved beneath it and shifted along it."""
    d = scene.distractors
    fit = rm.layout.surface
    bars = (None if fit is None else [b for b in rm.bars if b.layer == fit.top_mat]) or rm.bars
    shapes = []
    for bar in bars:
        c = bar.curve
        if c.kind == "line":
            s = np.array([0.0, c.length])
        else:  # chord error under 1 mm
            step = 2.0 * np.sqrt(2.0 * c.radius * 1e-3)
            s = np.linspace(0.0, c.length, max(2, int(np.ceil(c.length / step)) + 1))
        pts = c.point(s)
        ab = surf.to_ab(pts) + np.array([d.lower_layer_shift_a_m, d.lower_layer_shift_b_m])
        h = surf.height(pts) - d.lower_layer_depth_m
        moved, _, _, normal = surf.frame(ab, h)
        shapes.append(polyline_tube(moved, bar.radius_m, up_hint=normal[0], sides=8))
    return [SceneObject("lower_layer", Shape.concat(shapes), "rebar", DISTRACTOR_ID)]


def _spacers(scene: SceneSample, rm: RebarMesh, ground: _GroundProbe, rng) -> list[SceneObject]:
    n_sp = scene.distractors.spacers
    if n_sp == 0 or len(rm.crossings) == 0:
        return []
    pick = rng.choice(len(rm.crossings), size=min(n_sp, len(rm.crossings)), replace=False)
    shapes = []
    for i in np.sort(pick):
        p = rm.crossings.point[i]
        n = rm.crossings.normal[i]
        top = p - n * 0.02  # under both bars of a 12 mm crossing, touching the lower one
        t, _ = ground(top[None], -n[None])
        gap = float(t[0]) if np.isfinite(t[0]) else 0.05
        height = min(gap, float(rng.uniform(0.03, 0.06)))  # holds the mat up where the ground is that close
        radius = float(rng.uniform(0.015, 0.03))
        shapes.append(cylinder(top - n * gap, n, radius, height, sides=12))
    return [SceneObject("spacers", Shape.concat(shapes), "concrete", DISTRACTOR_ID)]


def _loose_wire(scene: SceneSample, surf: MatSurface, ground: _GroundProbe, rng) -> list[SceneObject]:
    n_w = scene.distractors.loose_tie_wire
    if n_w == 0:
        return []
    lo, hi = surf.bounds()
    ab = rng.uniform(lo - 0.3, hi + 0.3, (n_w, 2))
    start, t_a, t_b, n = surf.frame(ab, 0.0)
    t, normals = ground(start, -n)
    shapes = []
    for k in range(n_w):
        if not np.isfinite(t[k]):
            continue
        gn = normals[k] if np.dot(normals[k], n[k]) > 0 else -normals[k]
        base = start[k] - n[k] * t[k]
        e1 = t_a[k] - np.dot(t_a[k], gn) * gn
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(gn, e1)
        length = rng.uniform(0.1, 0.3)
        heading = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0, 0.35, 16))
        steps = length / 16 * np.stack([np.cos(heading), np.sin(heading)], 1)
        xy = np.concatenate([[[0.0, 0.0]], np.cumsum(steps, 0)])
        radius = 0.0008
        pts = base + xy[:, :1] * e1 + xy[:, 1:] * e2 + gn * radius * 1.5
        shapes.append(polyline_tube(pts, radius, up_hint=gn, sides=6))
    if not shapes:
        return []
    return [SceneObject("loose_tie_wire", Shape.concat(shapes), "tie_wire", DISTRACTOR_ID)]


def _formwork(scene: SceneSample, surf: MatSurface, ground: _GroundProbe) -> list[SceneObject]:
    sides = scene.distractors.formwork_sides
    if sides == 0:
        return []
    lo, hi = surf.bounds()
    gap, thick = 0.08, 0.02
    top_h = surf.height_range_m[1] + 0.03
    shapes = []
    for bit, (axis, end) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        if not sides & (1 << bit):
            continue
        along = 1 - axis
        fixed = (lo[axis] - gap) if end == 0 else (hi[axis] + gap)
        run = np.linspace(lo[along] - gap, hi[along] + gap, 24 if surf.is_tunnel and along == 1 else 2)
        ab = np.zeros((len(run), 2))
        ab[:, axis], ab[:, along] = fixed, run
        top, t_a, t_b, n = surf.frame(ab, top_h)
        t, _ = ground(top, -n)
        depth = np.where(np.isfinite(t), t, 0.5) + 0.02
        outward = (t_a if axis == 0 else t_b) * (1.0 if end == 1 else -1.0)
        for offset in (0.0, thick):
            upper = top + outward * offset
            lower = upper - n * depth[:, None]
            pts = np.stack([upper, lower], axis=1)
            heights = np.stack([np.zeros_like(depth), -depth], axis=1)
            uv = np.stack(np.broadcast_arrays(run[:, None], heights), axis=-1)
            face = grid(pts, uv)
            normal = np.cross(pts[1, 0] - pts[0, 0], pts[0, 1] - pts[0, 0])
            want = outward[0] if offset > 0 else -outward[0]
            if np.dot(normal, want) < 0:
                face = grid(pts, uv, flip=True)
            shapes.append(face)
        # the board's top edge
        edge = np.stack([top, top + outward * thick], axis=1)
        uv = np.stack(np.broadcast_arrays(run[:, None], np.array([0.0, thick])[None, :]), axis=-1)
        face = grid(edge, uv)
        if np.dot(np.cross(edge[1, 0] - edge[0, 0], edge[0, 1] - edge[0, 0]), n[0]) < 0:
            face = grid(edge, uv, flip=True)
        shapes.append(face)
    return [SceneObject("formwork", Shape.concat(shapes), "plywood", DISTRACTOR_ID)]


def build_surroundings(
    scene: SceneSample, rm: RebarMesh, surf: MatSurface | None = None
) -> list[SceneObject]:
    """Ground and distractor objects of ``scene`` around ``rm`` (deterministic in the sample)."""
    surf = surf if surf is not None else MatSurface.of(rm)
    rng = np.random.default_rng(scene.distractors.seed)
    ground = _ground(scene, surf, rm)
    objects = list(ground)
    probe = _GroundProbe(ground)
    if scene.distractors.lower_layer:
        objects += _lower_layer(scene, surf, rm)
    objects += _spacers(scene, rm, probe, rng)
    objects += _loose_wire(scene, surf, probe, rng)
    objects += _formwork(scene, surf, probe)
    return objects
