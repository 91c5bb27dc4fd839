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
from scipy.spatial import cKDTree

from rebar_data.geometry.curves import Curve, closest_points, sample
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
    # a mesh read from IFC, whose bars may have several pieces: the index in ``layout.bars`` of the piece of
    # each bar the crossing lies on (None where bar ids are those indices, as for every generated mesh)
    piece_a: np.ndarray | None = None
    piece_b: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.bar_a)

    def take(self, rows: np.ndarray) -> Crossings:
        """The crossings at ``rows`` (indices or a boolean mask), in that order."""
        pick = {
            name: None if getattr(self, name) is None else getattr(self, name)[rows]
            for name in self.__dataclass_fields__
        }
        return Crossings(**pick)


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


def candidate_pairs(
    curves: list[Curve], pads: np.ndarray, chunk_m: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)``, i < j, of curves that may come within ``pads[i] + pads[j]`` of each other.

    Each curve is cut into chunks of at most ``chunk_m`` of arc length, each held in a sphere (centred at
    the chunk's middle, radius half its length plus the pad: no point of a chunk lies farther from its middle
    along the curve, let alone in space); a k-d tree finds the pairs of spheres that meet. The cost grows
    with the number of chunks near one another, not with the square of the number of curves.
    Sorted by (i, j).
    """
    n = len(curves)
    if n < 2:
        z = np.zeros(0, np.int64)
        return z, z
    lengths = np.array([c.length for c in curves])
    counts = np.maximum(1, np.ceil(lengths / chunk_m).astype(np.int64))
    owner = np.repeat(np.arange(n), counts)
    half = np.repeat(lengths / counts / 2.0, counts)
    local = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
    s_mid = (2.0 * local + 1.0) * half
    centres = np.empty((len(owner), 3))
    start = np.cumsum(counts) - counts
    for i, c in enumerate(curves):
        centres[start[i] : start[i] + counts[i]] = c.point(s_mid[start[i] : start[i] + counts[i]])
    reach = (half + np.asarray(pads, float)[owner]) * (1.0 + 1e-9) + 1e-12  # never lose a pair to rounding
    pairs = cKDTree(centres).query_pairs(2.0 * float(reach.max()), output_type="ndarray")
    if len(pairs) == 0:
        z = np.zeros(0, np.int64)
        return z, z
    p, q = pairs[:, 0], pairs[:, 1]
    near = np.linalg.norm(centres[p] - centres[q], axis=1) <= reach[p] + reach[q]
    a, b = owner[p[near]], owner[q[near]]
    keep = a != b
    i, j = np.minimum(a[keep], b[keep]), np.maximum(a[keep], b[keep])
    key = np.unique(i * n + j)
    return key // n, key % n


def _oriented_normal(ta: np.ndarray, tb: np.ndarray) -> np.ndarray:
    """Unit normal of two crossing bars' tangents, pointing up (+z; for a vertical mat +x, then +y)."""
    n = np.cross(ta, tb)
    n = n / np.linalg.norm(n)
    for k in (2, 0, 1):
        if abs(n[k]) > 1e-9:
            return n if n[k] > 0 else -n
    return n


def find_piece_crossings(layout: MeshLayout, tolerance_m: float, min_angle_deg: float) -> Crossings:
    """Crossings of a mesh whose bars may have several pieces (read from IFC) and no known directions.

    Every pair of pieces of different bars is a candidate (:func:`candidate_pairs`); its closest points are
    exact (:func:`closest_points`), and it crosses where they are within the two radii plus ``tolerance_m``
    and the two tangents there meet at ``min_angle_deg`` or more (bars lapped side by side do not cross).
    Where one bar pair meets on two pieces of a bar (at the joint of a bend) the nearer is kept. The normal
    is the unit normal of both tangents, pointing up. Rows are ordered by (bar_a, bar_b, place on bar a).
    """
    pieces = layout.bars
    bar_id = np.array([b.bar_id for b in pieces], np.int64)
    pads = np.array([b.radius_m for b in pieces]) + tolerance_m / 2.0
    ii, jj = candidate_pairs([b.curve for b in pieces], pads)
    other = bar_id[ii] != bar_id[jj]
    ii, jj = ii[other], jj[other]
    cos_max = np.cos(np.radians(min_angle_deg))
    rows = []
    for i, j in zip(ii.tolist(), jj.tolist(), strict=True):
        a, b = pieces[i], pieces[j]
        if a.bar_id > b.bar_id:
            i, j, a, b = j, i, b, a
        s_a, s_b, pa, pb = closest_points(a.curve, b.curve)
        dist = float(np.linalg.norm(pa - pb))
        if dist > a.radius_m + b.radius_m + tolerance_m:
            continue
        ta, tb = a.curve.tangent(s_a), b.curve.tangent(s_b)
        if abs(float(np.dot(ta, tb))) > cos_max:
            continue
        rows.append((a.bar_id, b.bar_id, i, j, s_a, pa, pb, dist, _oriented_normal(ta, tb)))
    kept: list[tuple] = []
    by_pair: dict[tuple[int, int], list[np.ndarray]] = {}
    for r in sorted(rows, key=lambda r: (r[0], r[1], r[7])):  # per bar pair, nearest first
        reach = 2.0 * (pieces[r[2]].radius_m + pieces[r[3]].radius_m) + tolerance_m
        mid = (r[5] + r[6]) / 2.0
        taken = by_pair.setdefault((r[0], r[1]), [])
        if all(np.linalg.norm(m - mid) > reach for m in taken):
            taken.append(mid)
            kept.append(r)
    kept.sort(key=lambda r: (r[0], r[1], r[2], r[4]))
    if not kept:
        empty = np.zeros((0, 3))
        z = np.zeros(0, np.int32)
        return Crossings(z, z, z, empty, empty, empty, empty, np.zeros(0), z, z)
    layer_a = np.array([pieces[r[2]].layer for r in kept], np.int32)
    layer_b = np.array([pieces[r[3]].layer for r in kept], np.int32)
    pa = np.array([r[5] for r in kept])
    pb = np.array([r[6] for r in kept])
    radii = np.array([pieces[r[2]].radius_m + pieces[r[3]].radius_m for r in kept])
    return Crossings(
        np.array([r[0] for r in kept], np.int32),
        np.array([r[1] for r in kept], np.int32),
        np.where(layer_a == layer_b, layer_a, -1).astype(np.int32),
        (pa + pb) / 2.0,
        pa,
        pb,
        np.array([r[8] for r in kept]),
        np.array([r[7] for r in kept]) - radii,
        np.array([r[2] for r in kept], np.int32),
        np.array([r[3] for r in kept], np.int32),
    )
