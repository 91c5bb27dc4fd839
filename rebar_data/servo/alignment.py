"""The tool square to the mat, its jaw across the crossing and the crossing itself: measured from the camera,
scored by the truth.

What the camera gives (:func:`measure_local_frame`): the pixels of the depth image around the tracked
crossing that lie on the front mat (within ``band_m`` of the crossing's depth, then of a least-squares plane
through them) are back-projected. Seen from the crossing, the points of the two bars lie along two lines of
that plane, so the histogram of their directions (weighted by distance, over 0-180 degrees) has two peaks,
the second at least ``min_bar_angle_deg`` from the first; a 3D line fitted to each bar's points gives its
direction, and the cross product of the two is the mat's normal, towards the camera (the plane only seeds
this: through the bars' visible surfaces it is biased, the two bars lying a diameter apart in depth). Where the
two lines meet (the midpoint of their closest points) is the crossing itself, to a tenth of a pixel, which the
visit servos on once it is measured (:class:`AlignmentEstimate`).

What the tool should do (:func:`desired_rotation`): its axis (the camera's optical axis, parallel to the
tool's) along the inward normal, its jaw (the tool's x axis, the camera's x) on the bisector of the two bars
nearest its present direction: a jaw line is the same turned by 180 degrees, and crossing bars have two
bisectors, so the nearest of the four is the least turn. ``jaw_to_bar_deg`` sets another angle to the bar.

What the simulator says (:class:`CrossingTruth`): the bars' exact tangents at each crossing and the mat's
normal there, from the bar centerlines. The true tilt is the angle between the tool's axis and the inward
normal; the true jaw error is the angle, in the mat's plane, between the jaw and the nearest bisector line
(so at most 45 degrees for square crossings).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import convolve1d

from rebar_data.camera import Intrinsics
from rebar_data.geometry.build import RebarMesh
from rebar_data.servo.config import AlignConfig
from rebar_data.servo.transforms import rotvec

BIN_DEG = 1.0


@dataclass(frozen=True)
class LocalFrame:
    """The mat around one crossing in the camera frame: its unit normal (towards the camera), the two bars'
    unit directions in its plane (None where the second bar was not resolved) and where the two bars' lines
    meet (the midpoint of their closest points; None with the bars)."""

    normal: np.ndarray
    bars: np.ndarray | None
    crossing: np.ndarray | None = None


def _plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    n = vt[2]
    return centroid, n if n @ centroid < 0 else -n  # towards the camera (the camera is at the origin)


def measure_local_frame(
    depth_m: np.ndarray,
    uv: np.ndarray,
    crossing_depth_m: float,
    camera: Intrinsics,
    *,
    radius_m: float = 0.07,
    band_m: float = 0.03,
    plane_tolerance_m: float = 0.02,
    min_points: int = 200,
    min_bar_angle_deg: float = 30.0,
    bar_width_m: float = 0.012,
) -> LocalFrame | None:
    """The local frame of the mat around the crossing at pixel ``uv`` and depth ``crossing_depth_m``, from the
    depth image alone; None where too few depth pixels lie on the front mat."""
    if not (np.all(np.isfinite(uv)) and np.isfinite(crossing_depth_m) and crossing_depth_m > 0):
        return None
    h, w = depth_m.shape
    r_px = int(np.ceil(radius_m * camera.fx / crossing_depth_m))
    cu, cv = int(round(float(uv[0]))), int(round(float(uv[1])))
    u0, u1, v0, v1 = max(cu - r_px, 0), min(cu + r_px + 1, w), max(cv - r_px, 0), min(cv + r_px + 1, h)
    if u0 >= u1 or v0 >= v1:
        return None
    patch = depth_m[v0:v1, u0:u1]
    vv, uu = np.nonzero((patch > 0) & (np.abs(patch - crossing_depth_m) < band_m))
    if len(uu) < min_points:
        return None
    z = patch[vv, uu]
    # a pixel's centre: pixel (i, j) spans [i, i + 1) x [j, j + 1) (docs/conventions.md)
    pts = camera.back_project(np.column_stack([uu + u0 + 0.5, vv + v0 + 0.5]), z)
    centre = camera.back_project(np.atleast_2d(uv), np.array([crossing_depth_m]))[0]
    near = np.linalg.norm(pts - centre, axis=1) < radius_m
    pts = pts[near]
    if len(pts) < min_points:
        return None
    c, n = _plane(pts)
    for _ in range(2):  # refit on the points near the plane: the lower mat and strays fall out
        keep = np.abs((pts - c) @ n) < plane_tolerance_m
        if keep.sum() < min_points:
            return None
        pts = pts[keep]
        c, n = _plane(pts)
    lines = _bar_lines(pts, centre, n, min_bar_angle_deg, bar_width_m)
    if lines is None:
        return LocalFrame(n, None)
    bars, through = lines
    # The bars' own directions fix the plane without the bias a plane through their visible surfaces has
    # (the two bars lie one bar diameter apart in depth, and only their camera-facing halves are seen).
    m = np.cross(bars[0], bars[1])
    m /= np.linalg.norm(m)
    m = m if m @ n > 0 else -m
    crossing = _meeting_point(through, bars)
    bars = bars - np.outer(bars @ m, m)
    return LocalFrame(m, bars / np.linalg.norm(bars, axis=1, keepdims=True), crossing)


def _meeting_point(through: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """The midpoint of the closest points of two 3D lines (a point each, a direction each). The bars' lines
    run along their visible surfaces a bar diameter apart in depth, so they never quite meet."""
    (p, q), (d, e) = through, dirs
    w = p - q
    a, b, c = d @ d, d @ e, e @ e
    denom = a * c - b * b  # > 0: the bars are at least min_bar_angle_deg apart
    s = (b * (e @ w) - c * (d @ w)) / denom
    t = (a * (e @ w) - b * (d @ w)) / denom
    return 0.5 * ((p + s * d) + (q + t * e))


def _bar_lines(
    pts: np.ndarray, centre: np.ndarray, n: np.ndarray, min_angle_deg: float, bar_width_m: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """The two bars' 3D lines: their unit directions (2, 3) and a point on each (2, 3). The two strongest
    directions of the points seen from the crossing in the plane, then a line fitted to the points of each
    bar."""
    e1 = np.cross(n, [0.0, 1.0, 0.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(n, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    d = pts - centre
    a, b = d @ e1, d @ e2
    r = np.hypot(a, b)
    # the crossing's own knot of bar and wire says nothing of the directions, and near it a wide bar's
    # points spread over tens of degrees (16 mm bars: within 12 mm of the crossing, 0-34 degrees off their
    # axis, which the histogram took for a second bar 30 degrees from the first): only the points where the
    # bars' lines are fitted count
    beyond = max(0.025, 2.0 * bar_width_m)
    far = r > beyond
    if far.sum() < 50:
        return None
    theta = np.degrees(np.arctan2(b[far], a[far])) % 180.0
    peaks = _two_directions(theta, r[far], min_angle_deg)
    if peaks is None:
        return None
    dirs, through = [], []
    for p in peaks:
        ang = np.radians((p + 0.5) * BIN_DEG)
        u = np.array([np.cos(ang), np.sin(ang)])
        off = np.abs(a * u[1] - b * u[0])  # distance from the line through the crossing, in the plane
        on = (off < 0.75 * bar_width_m + 0.003) & far
        if on.sum() < 30:
            return None
        mean = pts[on].mean(axis=0)
        _, _, vt = np.linalg.svd(pts[on] - mean, full_matrices=False)
        dirs.append(vt[0])
        through.append(mean)
    return np.array(dirs), np.array(through)


def _two_directions(
    theta_deg: np.ndarray, weight: np.ndarray, min_angle_deg: float
) -> tuple[int, int] | None:
    """The bins (of :data:`BIN_DEG`, over 0-180 degrees) of the two bars' directions: the highest peak of the
    smoothed, weighted histogram of ``theta_deg``, and the highest other peak at least ``min_angle_deg`` from
    it (None where that is under a tenth of the first). The second must be a peak of its own: a wide bar's
    points spread its peak, and the highest bin ``min_angle_deg`` away can lie on that peak's flank (on the
    16 mm deck a "bar" 28-30 degrees from the first, the jaw 12-22 degrees off: docs/servo.md)."""
    nbins = int(round(180.0 / BIN_DEG))
    hist = np.bincount((theta_deg / BIN_DEG).astype(int) % nbins, weights=weight, minlength=nbins)
    kernel = np.exp(-0.5 * (np.arange(-6, 7) / 2.0) ** 2)
    smooth = convolve1d(hist, kernel, mode="wrap")  # angles wrap at 180 degrees
    p1 = int(np.argmax(smooth))
    dist = np.abs(((np.arange(nbins) - p1) * BIN_DEG + 90.0) % 180.0 - 90.0)
    peak = (smooth >= np.roll(smooth, 1)) & (smooth >= np.roll(smooth, -1))
    masked = np.where((dist >= min_angle_deg) & peak, smooth, -1.0)
    p2 = int(np.argmax(masked))
    if masked[p2] < 0.1 * smooth[p1]:
        return None
    return p1, p2


def jaw_lines(bars: np.ndarray, jaw_to_bar_deg: float | None) -> list[np.ndarray]:
    """The directions the jaw may take (unit vectors in the plane, each line once): the bars' two bisectors,
    or the lines ``jaw_to_bar_deg`` from either bar."""
    d1, d2 = bars[0], bars[1]
    if jaw_to_bar_deg is None:
        lines = [d1 + d2, d1 - d2]
    else:
        n = np.cross(d1, d2)
        n /= np.linalg.norm(n)
        t = np.radians(jaw_to_bar_deg)
        lines = [np.cos(t) * d + np.sin(s * t) * np.cross(n, d) for d in (d1, d2) for s in (1, -1)]
    return [v / np.linalg.norm(v) for v in lines if np.linalg.norm(v) > 1e-9]


def desired_rotation(normal: np.ndarray, bars: np.ndarray | None, jaw_to_bar_deg: float | None) -> np.ndarray:
    """The camera's desired orientation in its present frame (columns x*, y*, z*): z* along the inward normal,
    x* on the jaw line nearest the present x (the present x, squared to the normal, without bars)."""
    z = -normal / np.linalg.norm(normal)
    x_now = np.array([1.0, 0.0, 0.0])
    if bars is None:
        candidates = [x_now]
    else:
        candidates = [s * v for v in jaw_lines(bars, jaw_to_bar_deg) for s in (1.0, -1.0)]
    x = max(candidates, key=lambda v: float((v - (v @ z) * z) @ x_now))
    x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def rotation_error(R_desired: np.ndarray) -> tuple[np.ndarray, float, float]:
    """``theta u`` of the turn to ``R_desired`` (camera frame), and its tilt (the optical axis' angle to the
    desired one) and jaw (the remaining turn about it) parts, in degrees."""
    tu = rotvec(R_desired)
    tilt = float(np.degrees(np.arccos(np.clip(R_desired[2, 2], -1.0, 1.0))))
    return tu, tilt, float(np.degrees(abs(tu[2])))


@dataclass(frozen=True)
class CrossingTruth:
    """Every crossing's exact bar tangents and inward-facing normal (world), from the bar centerlines."""

    tangent_a: np.ndarray
    tangent_b: np.ndarray
    normal: np.ndarray

    @staticmethod
    def of(rm: RebarMesh) -> CrossingTruth:
        c = rm.crossings
        pieces_a = c.piece_a if c.piece_a is not None else c.bar_a
        pieces_b = c.piece_b if c.piece_b is not None else c.bar_b
        bars = rm.layout.bars

        def tangent(piece: int, p: np.ndarray) -> np.ndarray:
            curve = bars[int(piece)].curve
            t = np.asarray(curve.tangent(curve.project(p)), float)
            return t / np.linalg.norm(t)

        ta = np.array([tangent(i, p) for i, p in zip(pieces_a, c.point_a, strict=True)]).reshape(-1, 3)
        tb = np.array([tangent(i, p) for i, p in zip(pieces_b, c.point_b, strict=True)]).reshape(-1, 3)
        return CrossingTruth(ta, tb, np.asarray(c.normal, float).reshape(-1, 3))

    def errors(
        self, crossing_id: int, world_from_tool: np.ndarray, jaw_to_bar_deg: float | None
    ) -> tuple[float, float]:
        """True (tilt, jaw) errors in degrees of a tool pose at crossing ``crossing_id`` (NaN without one)."""
        if crossing_id < 0:
            return float("nan"), float("nan")
        axis, jaw = world_from_tool[:3, 2], world_from_tool[:3, 0]
        n = self.normal[crossing_id]
        tilt = float(np.degrees(np.arccos(np.clip(axis @ -n, -1.0, 1.0))))
        jaw_in_plane = jaw - (jaw @ n) * n
        jaw_in_plane /= np.linalg.norm(jaw_in_plane)
        bars = np.array([self.tangent_a[crossing_id], self.tangent_b[crossing_id]])
        bars = bars - np.outer(bars @ n, n)
        bars /= np.linalg.norm(bars, axis=1, keepdims=True)
        lines = jaw_lines(bars, jaw_to_bar_deg)
        jaw_err = min(float(np.degrees(np.arccos(np.clip(abs(jaw_in_plane @ v), 0.0, 1.0)))) for v in lines)
        return tilt, jaw_err


class AlignmentEstimate:
    """The running estimate of one target's desired tool orientation, kept in the world frame (by the
    controller's own pose estimate) so that the camera's motion does not blur it: each frame's measurement
    (:func:`measure_local_frame`, :func:`desired_rotation`) enters with weight ``smoothing``.

    Also the running estimate of where the two bars' lines meet (world frame; a running mean over the first
    ``1 / smoothing`` frames with both bars, then the same weight), and the point the visit servos on
    (:meth:`servo_point`): the tracked detection, until it and the lines' meeting point disagree by more than
    ``cfg.line_switch_px`` for ``SWITCH_FRAMES`` frames running; from then on, for the rest of the visit, the
    lines' meeting point. The lines are fitted to hundreds of depth pixels along each bar, so their meeting
    point lies within 0.1 px of the true crossing on ray-cast frames with structured-light depth, where the
    detector places crossings 0.35-0.9 px off (1.7-3.4 px where a bar ends just past the crossing, at a mat's
    edge); the detector finds the crossing, tracks it, and tells the top mat's from the lower one's."""

    SWITCH_FRAMES = 3

    def __init__(self, camera: Intrinsics, cfg: AlignConfig, *, depth_offset_m: float):
        self.camera, self.depth_offset_m = camera, depth_offset_m
        self.radius_m, self.smoothing, self.jaw_to_bar_deg = cfg.radius_m, cfg.smoothing, cfg.jaw_to_bar_deg
        self.line_switch_px = cfg.line_switch_px
        self.world_desired: np.ndarray | None = None  # (3, 3): x*, y*, z* as columns, world frame
        self.with_bars = False  # whether the estimate holds a frame with both bars resolved
        self.world_crossing: np.ndarray | None = None  # where the bars' lines meet, world frame
        self._crossings_seen = 0
        self._disagreeing = 0
        self.on_lines = False  # whether the visit now servos on the lines' meeting point

    def update(
        self, depth_m: np.ndarray, uv: np.ndarray, crossing_depth_m: float, world_from_camera: np.ndarray
    ) -> np.ndarray | None:
        """Take this frame's measurement in; the desired orientation in the camera's present frame (None
        until a first measurement)."""
        R_now = world_from_camera[:3, :3]
        local = measure_local_frame(
            depth_m,
            uv,
            crossing_depth_m - self.depth_offset_m,
            self.camera,
            radius_m=max(self.radius_m, 5.0 * self.depth_offset_m),  # heavy bars: a wider look
            plane_tolerance_m=max(0.02, 2.0 * self.depth_offset_m),
            bar_width_m=self.depth_offset_m,
        )
        if local is not None and local.crossing is not None:
            p = R_now @ local.crossing + world_from_camera[:3, 3]
            self._crossings_seen += 1
            a = max(1.0 / self._crossings_seen, self.smoothing)
            self.world_crossing = p if self.world_crossing is None else (1 - a) * self.world_crossing + a * p
        if local is not None and (local.bars is not None or self.world_desired is None):
            # a plane through the bars' visible surfaces alone is biased by their two depths: it only starts
            # an estimate, which frames with both bars resolved then carry
            R_cam = desired_rotation(local.normal, local.bars, self.jaw_to_bar_deg)
            R_world = R_now @ R_cam
            if self.world_desired is None or not self.with_bars:
                self.world_desired = R_world
                self.with_bars = local.bars is not None
            else:
                a = self.smoothing
                z = (1 - a) * self.world_desired[:, 2] + a * R_world[:, 2]
                x_new = R_world[:, 0]
                if x_new @ self.world_desired[:, 0] < 0:
                    x_new = -x_new
                x = (1 - a) * self.world_desired[:, 0] + a * x_new
                z /= np.linalg.norm(z)
                x = x - (x @ z) * z
                x /= np.linalg.norm(x)
                self.world_desired = np.column_stack([x, np.cross(z, x), z])
        if self.world_desired is None:
            return None
        return R_now.T @ self.world_desired

    def lines_px(self, world_from_camera: np.ndarray) -> np.ndarray | None:
        """The bars' lines' meeting point in the present image (None before both bars were resolved)."""
        if self.world_crossing is None:
            return None
        p = world_from_camera[:3, :3].T @ (self.world_crossing - world_from_camera[:3, 3])
        return self.camera.project(p[None])[0] if p[2] > 0 else None

    def servo_point(self, tracked_px: np.ndarray, world_from_camera: np.ndarray) -> np.ndarray:
        """The image point the visit servos on this frame: the tracked detection, or (once switched, see the
        class) the lines' meeting point."""
        lines = self.lines_px(world_from_camera)
        if lines is None or self.line_switch_px is None:
            return tracked_px
        if not self.on_lines:
            far = float(np.linalg.norm(lines - tracked_px)) > self.line_switch_px
            self._disagreeing = self._disagreeing + 1 if far else 0
            self.on_lines = self._disagreeing >= self.SWITCH_FRAMES
        return lines if self.on_lines else tracked_px
