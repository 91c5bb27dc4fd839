"""Keypoint labels for one frame: every crossing projected exactly, with visibility by a ray test.

Where a crossing is in the image: the two bars lie one above the other, so their centerlines' closest
points (and the midpoint between them, the crossing's point in ``crossings.parquet``) are inside the
metal, and under an oblique view that midpoint projects up to ``bar radius * sin(view angle)`` away from
where the bars are seen to cross (a mean 3.9 px, up to 9 px, over the paper-tunnel test frames). The
label is what the image shows: the pixel where the two projected centerlines cross. Its 3D point is the
sight point: on the camera's ray that meets both centerlines, the point on the nearer bar's centerline
(:func:`sight_points`). Seen along the normal it is the crossing's point; it never leaves the nearer
bar. The tables keep both: ``x_world`` .. of the sight point (so ``u, v`` reproject from it) and
``x_crossing`` .. of the crossing's fixed point.

Visibility follows COCO and Ultralytics: 0 when the crossing projects outside the image (or behind the
camera); 2 when the first hit along the ray from the camera centre to the crossing is one of the
crossing's own parts near the crossing (its tie wire, or either bar within ``near_diameters`` bar
diameters of the crossing measured along that bar), or lies beyond the crossing (the ray slipped through
the gap between two bars that do not quite touch: nothing is in front); 1 otherwise, when something
else, or the crossing's own bar far from it (seen along its length), is hit first. Measuring "near"
along the bar keeps a crossing seen at a grazing angle across its bars visible (the ray runs a long way
through the top bar there) while one hidden behind its own bar, seen along it, is occluded.

Each keypoint also gets a square detection box centred on it, so the same labels serve detection
and pose training. Its side is ``box_bar_diameters`` times the larger projected bar diameter at the
crossing's depth, and never less than ``min_box_px``:
``box_size_px = max(min_box_px, box_bar_diameters * (fx + fy) / 2 * max(d_a, d_b) / depth)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rebar_data.geometry.build import RebarMesh
from rebar_data.labels.projection import project

BEYOND_TOLERANCE_M = 1e-4  # a first hit this close to the crossing, or past it, is not in front of it
CastRays = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class LabelRule:
    box_bar_diameters: float = 4.0
    min_box_px: float = 8.0
    near_diameters: float = 3.0


@dataclass(frozen=True)
class CrossingParts:
    """For each crossing, the part ids that count as "its own" for the visibility test (padded with -9)."""

    own: np.ndarray  # (N, 3) int32: part of bar a, part of bar b, tie wire part or -9
    diameter_max_m: np.ndarray  # (N,)
    tangent_a: np.ndarray  # (N, 3) unit tangent of bar a at its closest point
    tangent_b: np.ndarray  # (N, 3) unit tangent of bar b at its closest point

    @staticmethod
    def of(rm: RebarMesh) -> CrossingParts:
        part_of_bar = np.full(len(rm.bars), -9, np.int32)
        tie_of_crossing = np.full(len(rm.crossings), -9, np.int32)
        for p in rm.parts:
            if p.kind == "bar":
                part_of_bar[p.bar_id] = p.part_id
            else:
                tie_of_crossing[p.crossing_id] = p.part_id
        c = rm.crossings
        own = np.stack([part_of_bar[c.bar_a], part_of_bar[c.bar_b], tie_of_crossing], axis=1)
        diam = np.array([b.diameter_m for b in rm.bars])

        def tangents(bars: np.ndarray, points: np.ndarray) -> np.ndarray:
            out = [
                rm.bars[b].curve.tangent(rm.bars[b].curve.project(p))
                for b, p in zip(bars, points, strict=True)
            ]
            return np.asarray(out, float).reshape(-1, 3)

        return CrossingParts(
            own,
            np.maximum(diam[c.bar_a], diam[c.bar_b]),
            tangents(c.bar_a, c.point_a),
            tangents(c.bar_b, c.point_b),
        )


@dataclass(frozen=True)
class FrameLabels:
    """Column arrays, one entry per crossing of the mesh (also those outside the view)."""

    u: np.ndarray
    v: np.ndarray
    visibility: np.ndarray  # int8
    depth_m: np.ndarray
    box_size_px: np.ndarray
    hit_instance: np.ndarray  # what the ray test hit first (-1 nothing), for the audit
    point_world: np.ndarray  # (N, 3) the sight point each label projects from (see the module)


SIGHT_MIN_SINE = 1e-6  # below this the camera's ray runs along a bar: the crossing's point is used
# a sight point farther than this (in bar diameters) from its crossing marks a view in which the two
# projected bars run nearly parallel and overlap over a long stretch (grazing views at image corners,
# 0.3% of the paper-tunnel's visible keypoints): no pixel is where they cross, and the crossing's point is used
SIGHT_MAX_OFFSET_DIAMETERS = 3.0


def sight_points_on_lines(
    point_a: np.ndarray,
    tangent_a: np.ndarray,
    point_b: np.ndarray,
    tangent_b: np.ndarray,
    camera_centre: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """For pairs of lines (N, 3 points and unit tangents), the point on the nearer line of the camera ray
    that meets both, and whether it is well defined (N,).

    With ``c`` the camera centre, the plane through ``c`` and line a meets line b at ``q_b``, the plane
    through ``c`` and line b meets line a at ``q_a``; both lie on one ray, which projects to where the
    two projected lines cross. Not defined where a ray runs along a line.
    """
    centre = np.asarray(camera_centre, float)
    pa, pb, ta, tb = (np.asarray(x, float) for x in (point_a, point_b, tangent_a, tangent_b))
    n_a = np.cross(ta, pa - centre)  # normal of the plane through the camera and line a
    n_b = np.cross(tb, pb - centre)
    den_b = np.einsum("ij,ij->i", n_a, tb)
    den_a = np.einsum("ij,ij->i", n_b, ta)
    scale_a = np.linalg.norm(n_a, axis=1) + 1e-300
    scale_b = np.linalg.norm(n_b, axis=1) + 1e-300
    ok = (np.abs(den_b) > SIGHT_MIN_SINE * scale_a) & (np.abs(den_a) > SIGHT_MIN_SINE * scale_b)
    with np.errstate(divide="ignore", invalid="ignore"):
        q_b = pb + (np.einsum("ij,ij->i", n_a, centre - pb) / den_b)[:, None] * tb
        q_a = pa + (np.einsum("ij,ij->i", n_b, centre - pa) / den_a)[:, None] * ta
    nearer_a = np.linalg.norm(q_a - centre, axis=1) <= np.linalg.norm(q_b - centre, axis=1)
    q = np.where(nearer_a[:, None], q_a, q_b)
    return q, ok & np.isfinite(q).all(axis=1)


def sight_points(rm: RebarMesh, parts: CrossingParts, camera_centre: np.ndarray) -> np.ndarray:
    """(N, 3) for every crossing, the point on the nearer bar's centerline where the camera's ray that
    meets both centerlines passes; it projects to where the two projected centerlines cross.

    Each centerline is its tangent line at the crossing (:func:`sight_points_on_lines`): an arc of
    radius R departs from it by s^2 / 2R where the sight point is s along it (with the paper's 3.2 m and
    12 mm bars: 35 um at a typical 15 mm, 0.14 mm at 30 mm in a grazing view, 0.1 px or less in the
    image). Where the geometry degenerates (a ray along a bar) the crossing's own point is returned, as
    it is where the sight point lies more than ``SIGHT_MAX_OFFSET_DIAMETERS`` bar diameters from the
    crossing.
    """
    c = rm.crossings
    q, ok = sight_points_on_lines(c.point_a, parts.tangent_a, c.point_b, parts.tangent_b, camera_centre)
    with np.errstate(invalid="ignore"):
        ok &= np.linalg.norm(q - c.point, axis=1) <= SIGHT_MAX_OFFSET_DIAMETERS * parts.diameter_max_m
    return np.where(ok[:, None], q, c.point)


def along_bar_distance(
    rm: RebarMesh,
    parts: CrossingParts,
    crossing: int,
    instance: int,
    point: np.ndarray,
    sight: np.ndarray,
) -> float:
    """How far ``point``, on part ``instance``, is from the crossing's sight point along that part.

    0 for the crossing's tie wire, the arc-length distance between the point's and the sight point's
    positions along the bar for either of its bars, and infinity for any other part. Measured from the
    sight point rather than the crossing: at a grazing view it runs several diameters along the nearer bar.
    """
    own = parts.own[crossing]
    if instance < 0 or instance not in own:
        return float("inf")
    if instance == own[2]:
        return 0.0
    c = rm.crossings
    curve = rm.bars[c.bar_a[crossing] if instance == own[0] else c.bar_b[crossing]].curve
    return abs(curve.project(point) - curve.project(sight))


def label_frame(
    rm: RebarMesh,
    parts: CrossingParts,
    world_from_camera: np.ndarray,
    intrinsics,
    cast_rays: CastRays,
    rule: LabelRule = LabelRule(),
) -> FrameLabels:
    """Project every crossing's sight point and decide its visibility with one batched ray cast."""
    k = intrinsics
    pts = sight_points(rm, parts, np.asarray(world_from_camera, float)[:3, 3])
    proj = project(pts, world_from_camera, fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy, width=k.width, height=k.height)
    n = len(pts)
    vis = np.zeros(n, np.int8)
    hit_instance = np.full(n, -1, np.int32)
    idx = np.nonzero(proj.in_image)[0]
    if len(idx):
        origin = world_from_camera[:3, 3]
        delta = pts[idx] - origin
        dist = np.linalg.norm(delta, axis=1)
        dirs = delta / dist[:, None]
        t_hit, inst = cast_rays(np.tile(origin, (len(idx), 1)), dirs)
        inst = np.asarray(inst, np.int32)
        hit = np.isfinite(t_hit)
        hit_point = origin + dirs * np.where(hit, t_hit, 0.0)[:, None]
        near = np.array(
            [
                hit[j]
                and along_bar_distance(rm, parts, int(c), int(inst[j]), hit_point[j], pts[c])
                <= rule.near_diameters * parts.diameter_max_m[c]
                for j, c in enumerate(idx)
            ],
            bool,
        )
        beyond = ~hit | (t_hit >= dist - BEYOND_TOLERANCE_M)
        vis[idx] = np.where(near | beyond, 2, 1)
        hit_instance[idx] = inst
    f = (k.fx + k.fy) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        box = rule.box_bar_diameters * f * parts.diameter_max_m / proj.depth_m
    box = np.where(proj.depth_m > 0, np.maximum(box, rule.min_box_px), 0.0)
    behind = proj.depth_m <= 0  # no meaningful pixel: stored as NaN
    u = np.where(behind, np.nan, proj.u)
    v = np.where(behind, np.nan, proj.v)
    return FrameLabels(u, v, vis, proj.depth_m, box, hit_instance, pts)
