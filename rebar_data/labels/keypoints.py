"""Keypoint labels for one frame: every crossing projected exactly, with visibility by a ray test.

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
        return CrossingParts(own, np.maximum(diam[c.bar_a], diam[c.bar_b]))


@dataclass(frozen=True)
class FrameLabels:
    """Column arrays, one entry per crossing of the mesh (also those outside the view)."""

    u: np.ndarray
    v: np.ndarray
    visibility: np.ndarray  # int8
    depth_m: np.ndarray
    box_size_px: np.ndarray
    hit_instance: np.ndarray  # what the ray test hit first (-1 nothing), for the audit


def along_bar_distance(
    rm: RebarMesh, parts: CrossingParts, crossing: int, instance: int, point: np.ndarray
) -> float:
    """How far ``point``, on part ``instance``, is from the crossing along that part.

    0 for the crossing's tie wire, the arc-length distance between the point's and the crossing's
    positions along the bar for either of its bars, and infinity for any other part.
    """
    own = parts.own[crossing]
    if instance < 0 or instance not in own:
        return float("inf")
    if instance == own[2]:
        return 0.0
    c = rm.crossings
    bar, closest = (
        (c.bar_a[crossing], c.point_a[crossing])
        if instance == own[0]
        else (c.bar_b[crossing], c.point_b[crossing])
    )
    curve = rm.bars[bar].curve
    return abs(curve.project(point) - curve.project(closest))


def label_frame(
    rm: RebarMesh,
    parts: CrossingParts,
    world_from_camera: np.ndarray,
    intrinsics,
    cast_rays: CastRays,
    rule: LabelRule = LabelRule(),
) -> FrameLabels:
    """Project every crossing and decide its visibility with one batched ray cast."""
    k = intrinsics
    pts = rm.crossings.point
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
                and along_bar_distance(rm, parts, int(c), int(inst[j]), hit_point[j])
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
    return FrameLabels(u, v, vis, proj.depth_m, box, hit_instance)
