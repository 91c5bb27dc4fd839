"""Crossing points, found analytically from the bar centerlines (never by sampling the triangle mesh).

For every pair of bars of different directions whose padded bounding boxes meet, the closest points of
the two centerlines are computed exactly (:func:`closest_points`). A crossing exists where those points
are within the sum of the two radii plus ``tolerance_m``. It is recorded at the midpoint of the two
closest points, with both bar ids, the layer, the element's outward normal there and the surface gap
(negative when the bars interpenetrate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rebar_data.geometry.curves import closest_points, sample
from rebar_data.geometry.specs import Bar, MeshLayout


@dataclass(frozen=True)
class Crossings:
    """Column arrays, one row per crossing, ordered by (bar_a, bar_b) with bar_a < bar_b."""

    bar_a: np.ndarray
    bar_b: np.ndarray
    layer: np.ndarray
    point: np.ndarray  # (N, 3) midpoint, world
    point_a: np.ndarray  # (N, 3) closest point on bar a's centerline
    point_b: np.ndarray  # (N, 3) closest point on bar b's centerline
    normal: np.ndarray  # (N, 3) outward unit normal of the element at the crossing
    gap_m: np.ndarray  # surface gap: centre distance minus the two radii

    def __len__(self) -> int:
        return len(self.bar_a)


def _bounds(bar: Bar, pad: float) -> tuple[np.ndarray, np.ndarray]:
    step = 0.05
    _, pts = sample(bar.curve, step)
    sag = 0.0
    if bar.curve.kind == "arc":  # chord sampling cuts the arc by at most its sagitta
        sag = bar.curve.radius * (1 - np.cos(step / (2 * bar.curve.radius)))
    return pts.min(0) - pad - sag, pts.max(0) + pad + sag


def find_crossings(layout: MeshLayout, tolerance_m: float) -> Crossings:
    bars = layout.bars
    boxes = [_bounds(b, b.radius_m + tolerance_m / 2) for b in bars]
    lo = np.array([bx[0] for bx in boxes]).reshape(-1, 3)
    hi = np.array([bx[1] for bx in boxes]).reshape(-1, 3)
    direction = np.array([b.direction for b in bars])
    overlap = np.all((lo[:, None, :] <= hi[None, :, :]) & (lo[None, :, :] <= hi[:, None, :]), axis=-1)
    candidate = np.triu(overlap & (direction[:, None] != direction[None, :]), k=1)
    rows = []
    for i, j in zip(*np.nonzero(candidate), strict=True):
        a, b = bars[i], bars[j]
        _, _, pa, pb = closest_points(a.curve, b.curve)
        dist = float(np.linalg.norm(pa - pb))
        if dist <= a.radius_m + b.radius_m + tolerance_m:
            rows.append((a.bar_id, b.bar_id, a.layer, pa, pb, dist - a.radius_m - b.radius_m))
    if not rows:
        empty = np.zeros((0, 3))
        z = np.zeros(0, np.int32)
        return Crossings(z, z, z, empty, empty, empty, empty, np.zeros(0))
    bar_a = np.array([r[0] for r in rows], np.int32)
    bar_b = np.array([r[1] for r in rows], np.int32)
    layer = np.array([r[2] for r in rows], np.int32)
    pa = np.array([r[3] for r in rows])
    pb = np.array([r[4] for r in rows])
    mid = (pa + pb) / 2.0
    return Crossings(
        bar_a, bar_b, layer, mid, pa, pb, layout.outward_normal(mid), np.array([r[5] for r in rows])
    )
