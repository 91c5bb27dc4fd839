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
diameters of the sight point measured along that bar); 1 otherwise: when something else, or the
crossing's own bar far from it (seen along its length), is hit first; when the ray reaches the sight
point without meeting the nearer bar (the sight point lies past that bar's end, where the image shows no
bar); and where no pixel shows the two bars cross (:func:`sight_points`: the projected bars meet at a
very shallow angle and overlap along a stretch), as no pixel is the crossing's to train or score on.
Measuring "near" along the bar keeps a crossing seen at a grazing angle across its bars visible (the ray runs a long way
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

from rebar_data.camera import Intrinsics, project
from rebar_data.geometry.build import RebarMesh
from rebar_data.geometry.curves import CurveArrays

CastRays = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class LabelRule:
    box_bar_diameters: float = 4.0
    min_box_px: float = 8.0
    near_diameters: float = 3.0


@dataclass(frozen=True)
class CrossingParts:
    """For each crossing, the parts that count as "its own" for the visibility test, and the pieces of its
    bars it lies on.

    A bar of a generated mesh is one piece and one part; a bar read from IFC may have several pieces (one
    part each) and a ball at each sharp joint. Every part of either bar is the crossing's own; distances
    along a bar run over all its pieces.
    """

    own: np.ndarray  # (N, 3) int32: part of piece a, part of piece b, tie wire part or -9
    diameter_max_m: np.ndarray  # (N,)
    tangent_a: np.ndarray  # (N, 3) unit tangent of bar a at its closest point
    tangent_b: np.ndarray  # (N, 3) unit tangent of bar b at its closest point
    bars: CurveArrays  # every piece's centerline, for the per-frame sight points (built once per mesh)
    piece_a: np.ndarray  # (N,) index in ``rm.bars`` of the piece of bar a the crossing lies on
    piece_b: np.ndarray  # (N,)
    part_bar: np.ndarray  # (parts,) bar id of each part, -1 for tie wire
    piece_start_m: np.ndarray  # (pieces,) arc length along its bar where each piece begins
    pieces_of_bar: dict[int, list[int]]  # bar id -> its pieces in ``rm.bars``, in order
    neighbours: np.ndarray  # (pieces, 3): each piece, the one before and after it on its bar (or itself)
    loop_length_m: dict[int, float]  # closed bars (a stirrup's loop): bar id -> length

    @staticmethod
    def of(rm: RebarMesh) -> CrossingParts:
        c = rm.crossings
        piece_a = np.asarray(c.bar_a if c.piece_a is None else c.piece_a, np.int64)
        piece_b = np.asarray(c.bar_b if c.piece_b is None else c.piece_b, np.int64)
        part_bar = np.array([p.bar_id if p.kind == "bar" else -1 for p in rm.parts], np.int64)
        tie_of_crossing = np.full(len(c), -9, np.int32)
        for p in rm.parts:
            if p.kind != "bar":
                tie_of_crossing[p.crossing_id] = p.part_id
        # the first len(rm.bars) parts are the pieces' tubes, in order (build_parts)
        own = np.stack([piece_a, piece_b, tie_of_crossing], axis=1).astype(np.int32)
        diam = np.array([b.diameter_m for b in rm.bars])
        pieces_of_bar: dict[int, list[int]] = {}
        start = np.zeros(len(rm.bars))
        for i, b in enumerate(rm.bars):
            done = pieces_of_bar.setdefault(b.bar_id, [])
            start[i] = sum(rm.bars[k].curve.length for k in done)
            done.append(i)

        neighbours = np.repeat(np.arange(len(rm.bars))[:, None], 3, axis=1)
        loop_length: dict[int, float] = {}
        for bar_id, pieces in pieces_of_bar.items():
            neighbours[pieces[1:], 1] = pieces[:-1]
            neighbours[pieces[:-1], 2] = pieces[1:]
            first, last = rm.bars[pieces[0]].curve, rm.bars[pieces[-1]].curve
            if len(pieces) > 1 and np.linalg.norm(last.point(last.length) - first.point(0.0)) < CLOSED_M:
                neighbours[pieces[0], 1], neighbours[pieces[-1], 2] = pieces[-1], pieces[0]
                loop_length[bar_id] = float(start[pieces[-1]] + last.length)

        def tangents(pieces: np.ndarray, points: np.ndarray) -> np.ndarray:
            out = [
                rm.bars[k].curve.tangent(rm.bars[k].curve.project(p))
                for k, p in zip(pieces, points, strict=True)
            ]
            return np.asarray(out, float).reshape(-1, 3)

        return CrossingParts(
            own,
            np.maximum(diam[piece_a], diam[piece_b]),
            tangents(piece_a, c.point_a),
            tangents(piece_b, c.point_b),
            CurveArrays.of([b.curve for b in rm.bars]),
            piece_a,
            piece_b,
            part_bar,
            start,
            pieces_of_bar,
            neighbours,
            loop_length,
        )

    def nearest_on_bar(
        self, pieces: np.ndarray, points: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For points (N, 3) near pieces (N,): the piece among each one and its neighbours on its bar that is
        nearest the point, the arc length of the point's foot on it, and the distance to that foot. A point
        past a piece's end at a bend lies on the next piece; on a bar of one piece this is that piece."""
        cand = self.neighbours[np.asarray(pieces, np.int64)]  # (N, 3)
        pts = np.repeat(np.asarray(points, float), 3, axis=0)
        flat = cand.reshape(-1)
        s = self.bars.project(flat, pts)
        d = np.linalg.norm(self.bars.point(flat, s) - pts, axis=1).reshape(-1, 3)
        k = np.argmin(d, axis=1)
        rows = np.arange(len(cand))
        return cand[rows, k], s.reshape(-1, 3)[rows, k], d[rows, k]

    def is_own(self, rm: RebarMesh, crossing: int, instance: int) -> bool:
        """Part ``instance`` is the crossing's tie wire or a part of either of its bars."""
        if instance < 0 or instance >= len(self.part_bar):
            return False
        if instance == self.own[crossing, 2]:
            return True
        return int(self.part_bar[instance]) in (
            int(rm.crossings.bar_a[crossing]),
            int(rm.crossings.bar_b[crossing]),
        )

    def along_bar_m(self, rm: RebarMesh, bar_id: int, point: np.ndarray) -> float:
        """Arc length along bar ``bar_id`` (over all its pieces) of the foot of ``point`` on it."""
        best_d, best_s = np.inf, 0.0
        for k in self.pieces_of_bar[bar_id]:
            curve = rm.bars[k].curve
            s = curve.project(point)
            d = float(np.linalg.norm(curve.point(s) - point))
            if d < best_d:
                best_d, best_s = d, float(self.piece_start_m[k] + s)
        return best_s


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
# projected bars that meet at a shallower angle than this overlap along a stretch of several bar widths (grazing
# views at image corners): no pixel is where they cross, and the crossing's point is used
SIGHT_MIN_ANGLE_DEG = 10.0
# curved bars: the sight point is found on the tangent lines, then again on the tangent lines at the points
# found, this many times (an arc departs from its tangent by s^2 / 2R: 9 mm for a sight point 0.23 m along a
# 3 m arc, 1e-5 m after 3 steps, 1e-15 m after 5)
SIGHT_CURVE_STEPS = 5
CLOSED_M = 1e-6  # a bar whose last piece ends this near its first piece's start is a closed loop
# the mat's outermost crossings lie at their bars' ends: a sight point up to this many bar diameters past a
# bar's end still shows the bars meet (at the end's cap); farther out the image shows no crossing
SIGHT_PAST_END_DIAMETERS = 1.0


def sight_lines(
    point_a: np.ndarray,
    tangent_a: np.ndarray,
    point_b: np.ndarray,
    tangent_b: np.ndarray,
    camera_centre: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For pairs of lines (N, 3 points and unit tangents): the points ``q_a`` on line a and ``q_b`` on
    line b of the camera ray that meets both, the sine of the angle at which the two lines' images cross,
    and whether the ray is defined (not along a line).

    With ``c`` the camera centre, the plane through ``c`` and line a meets line b at ``q_b``, the plane
    through ``c`` and line b meets line a at ``q_a``; both lie on one ray, which projects to where the
    two projected lines cross. The two planes meet along that ray at the angle the projected lines make
    (exactly so on a spherical image; on the image plane near its centre).
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
    sine = np.linalg.norm(np.cross(n_a, n_b), axis=1) / (scale_a * scale_b)
    with np.errstate(divide="ignore", invalid="ignore"):
        q_b = pb + (np.einsum("ij,ij->i", n_a, centre - pb) / den_b)[:, None] * tb
        q_a = pa + (np.einsum("ij,ij->i", n_b, centre - pa) / den_a)[:, None] * ta
    ok &= np.isfinite(q_a).all(axis=1) & np.isfinite(q_b).all(axis=1)
    return q_a, q_b, sine, ok


def _nearer(q_a: np.ndarray, q_b: np.ndarray, camera_centre: np.ndarray) -> np.ndarray:
    centre = np.asarray(camera_centre, float)
    nearer_a = np.linalg.norm(q_a - centre, axis=1) <= np.linalg.norm(q_b - centre, axis=1)
    return np.where(nearer_a[:, None], q_a, q_b)


def sight_points_on_lines(
    point_a: np.ndarray,
    tangent_a: np.ndarray,
    point_b: np.ndarray,
    tangent_b: np.ndarray,
    camera_centre: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """For pairs of lines (N, 3 points and unit tangents), the point on the nearer line of the camera ray
    that meets both (:func:`sight_lines`), and whether it is well defined (N,): the ray is not along a
    line and the lines' images cross at ``SIGHT_MIN_ANGLE_DEG`` or more.
    """
    q_a, q_b, sine, ok = sight_lines(point_a, tangent_a, point_b, tangent_b, camera_centre)
    ok &= sine >= np.sin(np.radians(SIGHT_MIN_ANGLE_DEG))
    return _nearer(q_a, q_b, camera_centre), ok


def sight_points(
    rm: RebarMesh, parts: CrossingParts, camera_centre: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) for every crossing, the point on the nearer bar's centerline where the camera's ray that
    meets both centerlines passes (it projects to where the two projected centerlines cross), and (N,)
    whether it is defined.

    It is found on each centerline's tangent line at the crossing (:func:`sight_lines`). Where a bar is
    curved, the tangent lines at the points found replace them, ``SIGHT_CURVE_STEPS`` times: an arc of
    radius R departs from its tangent by s^2 / 2R where the sight point is s along it, which under a
    grazing view (s several bar diameters) would put it a millimetre or more off the bar. On a bar of several
    pieces (read from IFC) they are the tangent lines of the piece nearest the points found: past a bend
    the sight point goes on along the next piece.

    Where no pixel shows the bars cross (a ray along a bar; projected bars meeting at less than
    ``SIGHT_MIN_ANGLE_DEG``: they overlap along a stretch, at grazing views near the image's corners; the
    ray meets a bar's centerline only more than ``SIGHT_PAST_END_DIAMETERS`` past the bar's end, at the
    mat's edge) the crossing's own point is returned and the second array is False; :func:`label_frame` marks such a
    keypoint occluded (1) at most. The sight point may lie several bar diameters along the bars from the
    crossing: at a grazing view across two stacked bars, the ray that meets both runs a long way between
    them (a label at the crossing's own point would lie in the gap between the bars' images, where the
    image shows no crossing).
    """
    c = rm.crossings
    centre = np.asarray(camera_centre, float)
    q_a, q_b, sine, ok = sight_lines(c.point_a, parts.tangent_a, c.point_b, parts.tangent_b, centre)
    bars = parts.bars
    a, b = parts.piece_a, parts.piece_b
    bent = (parts.neighbours[:, 1:] != np.arange(len(parts.neighbours))[:, None]).any(axis=1)
    curved = np.flatnonzero(ok & (bars.is_arc[a] | bars.is_arc[b] | bent[a] | bent[b]))
    for _ in range(SIGHT_CURVE_STEPS if len(curved) else 0):
        ia, sa, _ = parts.nearest_on_bar(a[curved], q_a[curved])
        ib, sb, _ = parts.nearest_on_bar(b[curved], q_b[curved])
        qa, qb, s_k, ok_k = sight_lines(
            bars.point(ia, sa), bars.tangent(ia, sa), bars.point(ib, sb), bars.tangent(ib, sb), centre
        )
        ok[curved] &= ok_k
        q_a[curved] = np.where(ok_k[:, None], qa, q_a[curved])
        q_b[curved] = np.where(ok_k[:, None], qb, q_b[curved])
        sine[curved] = np.where(ok_k, s_k, sine[curved])
    # both points on their bars, not on a line's extension past a bar's end (no crossing is drawn there)
    with np.errstate(invalid="ignore"):
        past = np.maximum(parts.nearest_on_bar(a, q_a)[2], parts.nearest_on_bar(b, q_b)[2])
        ok &= past <= SIGHT_PAST_END_DIAMETERS * parts.diameter_max_m
    ok &= sine >= np.sin(np.radians(SIGHT_MIN_ANGLE_DEG))
    return np.where(ok[:, None], _nearer(q_a, q_b, centre), c.point), ok


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
    if not parts.is_own(rm, crossing, instance):
        return float("inf")
    if instance == parts.own[crossing, 2]:
        return 0.0
    bar = int(parts.part_bar[instance])
    d = abs(parts.along_bar_m(rm, bar, point) - parts.along_bar_m(rm, bar, sight))
    loop = parts.loop_length_m.get(bar)
    return d if loop is None else min(d, loop - d)  # round a closed bar, the shorter way


def label_frame(
    rm: RebarMesh,
    parts: CrossingParts,
    world_from_camera: np.ndarray,
    intrinsics: Intrinsics,
    cast_rays: CastRays,
    rule: LabelRule = LabelRule(),
) -> FrameLabels:
    """Project every crossing's sight point and decide its visibility with one batched ray cast."""
    k = intrinsics
    pts, seen = sight_points(rm, parts, np.asarray(world_from_camera, float)[:3, 3])
    proj = project(pts, world_from_camera, k)
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
        vis[idx] = np.where(near & seen[idx], 2, 1)
        hit_instance[idx] = inst
    f = (k.fx + k.fy) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        box = rule.box_bar_diameters * f * parts.diameter_max_m / proj.depth_m
    box = np.where(proj.depth_m > 0, np.maximum(box, rule.min_box_px), 0.0)
    behind = proj.depth_m <= 0  # no meaningful pixel: stored as NaN
    u = np.where(behind, np.nan, proj.u)
    v = np.where(behind, np.nan, proj.v)
    return FrameLabels(u, v, vis, proj.depth_m, box, hit_instance, pts)
