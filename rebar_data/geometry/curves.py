"""Bar centerlines: straight lines and circular arcs, and the exact closest points between two of them.

Both curve types are parametrised by arc length ``s`` in ``[0, length]`` and have a closed-form
projection of a point onto the curve. The closest points between two curves are found by alternating
those exact projections from the best pair of samples; for bars that cross at a clear angle this
converges in a handful of steps to machine precision, and every returned point is evaluated on its
curve, so it lies on the centerline by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_TWO_PI = 2.0 * np.pi


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    if n == 0.0:
        raise ValueError("zero-length direction")
    return v / n


@dataclass(frozen=True)
class Line:
    """Straight centerline from ``start`` to ``end`` (metres)."""

    start: np.ndarray
    end: np.ndarray

    kind = "line"

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.end - self.start))

    @property
    def direction(self) -> np.ndarray:
        return _unit(self.end - self.start)

    def point(self, s: np.ndarray | float) -> np.ndarray:
        s = np.asarray(s, float)
        return self.start + s[..., None] * self.direction

    def tangent(self, s: np.ndarray | float) -> np.ndarray:
        s = np.asarray(s, float)
        return np.broadcast_to(self.direction, s.shape + (3,)).copy()

    def project(self, p: np.ndarray) -> float:
        """Arc length of the point of the line segment closest to ``p``."""
        s = float(np.dot(p - self.start, self.direction))
        return min(max(s, 0.0), self.length)

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> Line:
        return Line(rotation @ self.start + translation, rotation @ self.end + translation)


@dataclass(frozen=True)
class Arc:
    """Circular arc: ``center + radius * (cos(phi) e1 + sin(phi) e2)`` for phi in ``[0, sweep]``.

    ``axis`` is the unit normal of the arc's plane; ``e1`` the unit vector from the center to the
    start point; ``e2 = axis x e1``, so the arc turns counter-clockwise about ``axis``.
    """

    center: np.ndarray
    radius: float
    axis: np.ndarray
    e1: np.ndarray
    sweep: float

    kind = "arc"

    @property
    def e2(self) -> np.ndarray:
        return np.cross(self.axis, self.e1)

    @property
    def length(self) -> float:
        return float(self.radius * self.sweep)

    @property
    def start(self) -> np.ndarray:
        return self.point(0.0)

    @property
    def end(self) -> np.ndarray:
        return self.point(self.length)

    def point(self, s: np.ndarray | float) -> np.ndarray:
        phi = np.asarray(s, float) / self.radius
        return self.center + self.radius * (
            np.cos(phi)[..., None] * self.e1 + np.sin(phi)[..., None] * self.e2
        )

    def tangent(self, s: np.ndarray | float) -> np.ndarray:
        phi = np.asarray(s, float) / self.radius
        return -np.sin(phi)[..., None] * self.e1 + np.cos(phi)[..., None] * self.e2

    def project(self, p: np.ndarray) -> float:
        """Arc length of the point of the arc closest to ``p``."""
        v = p - self.center
        x, y = float(np.dot(v, self.e1)), float(np.dot(v, self.e2))
        if x == 0.0 and y == 0.0:  # on the axis: every point is equally near
            return 0.0
        phi = np.arctan2(y, x) % _TWO_PI
        if phi > self.sweep:  # outside the arc: the nearer end, measured around the circle
            to_end = phi - self.sweep
            to_start = _TWO_PI - phi
            phi = self.sweep if to_end < to_start else 0.0
        return float(phi * self.radius)

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> Arc:
        return Arc(
            rotation @ self.center + translation,
            self.radius,
            rotation @ self.axis,
            rotation @ self.e1,
            self.sweep,
        )

    @staticmethod
    def through(start: np.ndarray, end: np.ndarray, bulge_dir: np.ndarray, sagitta: float) -> Arc:
        """Arc from ``start`` to ``end`` whose midpoint is displaced by ``sagitta`` along ``bulge_dir``."""
        chord = end - start
        half = np.linalg.norm(chord) / 2.0
        bulge = _unit(bulge_dir - np.dot(bulge_dir, chord) / np.dot(chord, chord) * chord)
        radius = (half**2 + sagitta**2) / (2.0 * sagitta)
        center = (start + end) / 2.0 - bulge * (radius - sagitta)
        e1 = _unit(start - center)
        axis = _unit(np.cross(start - center, end - center))
        sweep = 2.0 * np.arcsin(min(half / radius, 1.0))
        return Arc(center, float(radius), axis, e1, float(sweep))


Curve = Line | Arc


@dataclass(frozen=True)
class CurveArrays:
    """Many curves at once, for per-frame work over every crossing: ``project``, ``point`` and ``tangent``
    of curve ``idx[k]`` at the k-th point or arc length, as :class:`Line` and :class:`Arc` give them one at
    a time (the same formulas, nearer end outside an arc's sweep included)."""

    is_arc: np.ndarray  # (M,) bool
    origin: np.ndarray  # (M, 3) a line's start, an arc's center
    e1: np.ndarray  # (M, 3) a line's direction, an arc's e1
    e2: np.ndarray  # (M, 3) an arc's e2 (0 for a line)
    radius: np.ndarray  # (M,) an arc's radius (1 for a line)
    length: np.ndarray  # (M,)

    @staticmethod
    def of(curves: list[Curve]) -> CurveArrays:
        arc = np.array([c.kind == "arc" for c in curves], bool)
        origin = np.array([c.center if c.kind == "arc" else c.start for c in curves], float).reshape(-1, 3)
        e1 = np.array([c.e1 if c.kind == "arc" else c.direction for c in curves], float).reshape(-1, 3)
        axis = np.array([c.axis if c.kind == "arc" else np.zeros(3) for c in curves], float).reshape(-1, 3)
        e2 = np.cross(axis, e1)  # an arc's axis x e1; 0 for a line
        radius = np.array([c.radius if c.kind == "arc" else 1.0 for c in curves], float)
        return CurveArrays(arc, origin, e1, e2, radius, np.array([c.length for c in curves], float))

    def project(self, idx: np.ndarray, p: np.ndarray) -> np.ndarray:
        v = p - self.origin[idx]
        x = np.einsum("ij,ij->i", v, self.e1[idx])
        y = np.einsum("ij,ij->i", v, self.e2[idx])
        r, length = self.radius[idx], self.length[idx]
        phi = np.arctan2(y, x) % _TWO_PI
        sweep = length / r
        outside = phi > sweep
        phi = np.where(outside, np.where(phi - sweep < _TWO_PI - phi, sweep, 0.0), phi)
        phi = np.where((x == 0.0) & (y == 0.0), 0.0, phi)
        return np.where(self.is_arc[idx], phi * r, np.clip(x, 0.0, length))

    def point(self, idx: np.ndarray, s: np.ndarray) -> np.ndarray:
        arc, r = self.is_arc[idx], self.radius[idx]
        phi = s / r
        on_arc = self.origin[idx] + r[:, None] * (
            np.cos(phi)[:, None] * self.e1[idx] + np.sin(phi)[:, None] * self.e2[idx]
        )
        on_line = self.origin[idx] + s[:, None] * self.e1[idx]
        return np.where(arc[:, None], on_arc, on_line)

    def tangent(self, idx: np.ndarray, s: np.ndarray) -> np.ndarray:
        phi = s / self.radius[idx]
        on_arc = -np.sin(phi)[:, None] * self.e1[idx] + np.cos(phi)[:, None] * self.e2[idx]
        return np.where(self.is_arc[idx][:, None], on_arc, self.e1[idx])


def sample(curve: Curve, max_step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Arc lengths and points at most ``max_step_m`` apart, ends included."""
    n = max(2, int(np.ceil(curve.length / max_step_m)) + 1)
    s = np.linspace(0.0, curve.length, n)
    return s, curve.point(s)


def closest_points(
    a: Curve, b: Curve, *, seed_step_m: float = 0.02, tol_m: float = 1e-15, max_iter: int = 500
) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Closest points of two bounded centerlines.

    Returns ``(s_a, s_b, point_a, point_b)``, each point evaluated on its own curve. The iteration
    starts from the nearest pair of samples, then alternates the exact point-to-curve projections
    until neither point moves by more than ``tol_m``.
    """
    if a.kind == "line" and b.kind == "line":
        return _segment_segment(a, b)
    sa, pa = sample(a, seed_step_m)
    sb, pb = sample(b, seed_step_m)
    d2 = ((pa[:, None, :] - pb[None, :, :]) ** 2).sum(-1)
    i, j = np.unravel_index(np.argmin(d2), d2.shape)
    s_a, s_b = float(sa[i]), float(sb[j])
    p_a = a.point(s_a)
    for _ in range(max_iter):
        s_b = b.project(p_a)
        p_b = b.point(s_b)
        s_a_new = a.project(p_b)
        p_a_new = a.point(s_a_new)
        moved = np.linalg.norm(p_a_new - p_a)
        s_a, p_a = s_a_new, p_a_new
        if moved <= tol_m:
            break
    s_b = b.project(p_a)
    return s_a, s_b, p_a, b.point(s_b)


def _segment_segment(a: Line, b: Line) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Closest points of two line segments (closed form, clamped to both segments)."""
    da, db = a.direction, b.direction
    r = a.start - b.start
    c = float(np.dot(da, db))
    denom = 1.0 - c * c
    e, f = float(np.dot(da, r)), float(np.dot(db, r))
    # parallel segments: any point will do, take the start of a
    s = np.clip((c * f - e) / denom, 0.0, a.length) if denom > 1e-15 else 0.0
    t = np.clip(c * s + f, 0.0, b.length)
    s = np.clip(c * t - e, 0.0, a.length)
    t = np.clip(c * s + f, 0.0, b.length)
    return float(s), float(t), a.point(s), b.point(t)
