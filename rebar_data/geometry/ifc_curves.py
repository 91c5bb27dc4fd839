"""Centerline pieces of IFC directrices, in the coordinates and length unit they are written in.

An IfcPolyline gives lines; an IfcTrimmedCurve of an IfcCircle (trimmed by parameter in the file's plane angle
unit, or by points) or a whole IfcCircle gives an arc, one of an IfcLine a line; an IfcIndexedPolyCurve gives
lines for its IfcLineIndex segments and arcs through the three points of its IfcArcIndex segments; an
IfcCompositeCurve gives its segments' pieces in order; an IfcSweptDiskSolidPolygonal's FilletRadius rounds
its polyline's corners into arcs (:func:`filleted`). Anything else raises :class:`Unreadable` saying why.
"""

from __future__ import annotations

import numpy as np

from rebar_data.geometry.curves import Arc, Curve, Line

MIN_LENGTH_M = 1e-9  # a shorter fillet leg is none
_TWO_PI = 2.0 * np.pi
_SCALE_TOL = 1e-6


class Unreadable(Exception):
    """A bar whose centerline the reader cannot make (the message says why)."""


def _xyz(coords) -> np.ndarray:
    p = np.zeros(3)
    c = [float(x) for x in coords]
    p[: len(c)] = c
    return p


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    n = float(np.linalg.norm(v))
    if n == 0.0 or not np.isfinite(n):
        raise Unreadable(f"a zero {what}")
    return v / n


def _frame(position) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Origin and orthonormal axes (x, y, z) of an IfcAxis2Placement2D/3D."""
    origin = _xyz(position.Location.Coordinates)
    axis = getattr(position, "Axis", None)
    z = _unit(_xyz(axis.DirectionRatios), "axis") if axis else np.array([0.0, 0.0, 1.0])
    ref = position.RefDirection
    x = _xyz(ref.DirectionRatios) if ref else np.array([1.0, 0.0, 0.0])
    x = x - np.dot(x, z) * z
    if np.linalg.norm(x) < 1e-12:  # RefDirection along the axis: IFC's default choice of x
        x = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = x - np.dot(x, z) * z
    x = _unit(x, "reference direction")
    return origin, x, cross(z, x), z


def _arc(center: np.ndarray, x, y, z, radius: float, start_rad: float, sweep_rad: float, ccw: bool) -> Arc:
    e1 = np.cos(start_rad) * x + np.sin(start_rad) * y
    return Arc(center, float(radius), z if ccw else -z, e1, float(sweep_rad))


def _sweep(a0: float, a1: float) -> float:
    """The turn from angle a0 to a1 counter-clockwise, in (0, 2 pi]."""
    s = (a1 - a0) % _TWO_PI
    return _TWO_PI if s == 0.0 and a1 != a0 else s


def _trim_angle(trims, master: str, origin, x, y, angle_rad: float) -> float:
    params = [t for t in trims if t.is_a() == "IfcParameterValue"]
    points = [t for t in trims if t.is_a() == "IfcCartesianPoint"]
    if points and (master == "CARTESIAN" or not params):
        v = _xyz(points[0].Coordinates) - origin
        return float(np.arctan2(np.dot(v, y), np.dot(v, x)))
    if params:
        return float(params[0].wrappedValue) * angle_rad
    raise Unreadable("an IfcTrimmedCurve without trims")


def _trimmed(c, angle_rad: float) -> list[Curve]:
    basis = c.BasisCurve
    master = c.MasterRepresentation or "UNSPECIFIED"
    if basis.is_a("IfcCircle"):
        origin, x, y, z = _frame(basis.Position)
        t1 = _trim_angle(c.Trim1, master, origin, x, y, angle_rad)
        t2 = _trim_angle(c.Trim2, master, origin, x, y, angle_rad)
        if c.SenseAgreement:
            return [_arc(origin, x, y, z, basis.Radius, t1, _sweep(t1, t2), True)]
        # clockwise from t1 to t2: counter-clockwise about the reversed axis, from the same start
        return [_arc(origin, x, -y, z, basis.Radius, -t1, _sweep(t2, t1), False)]
    if basis.is_a("IfcLine"):
        p0 = _xyz(basis.Pnt.Coordinates)
        d = _xyz(basis.Dir.Orientation.DirectionRatios)
        d = d / np.linalg.norm(d) * float(basis.Dir.Magnitude)

        def at(trims) -> np.ndarray:
            pts = [t for t in trims if t.is_a() == "IfcCartesianPoint"]
            params = [t for t in trims if t.is_a() == "IfcParameterValue"]
            if pts and (master == "CARTESIAN" or not params):
                return _xyz(pts[0].Coordinates)
            if params:
                return p0 + float(params[0].wrappedValue) * d
            raise Unreadable("an IfcTrimmedCurve without trims")

        a, b = at(c.Trim1), at(c.Trim2)
        return [Line(a, b) if c.SenseAgreement else Line(b, a)]
    raise Unreadable(f"an IfcTrimmedCurve of an {basis.is_a()}")


def arc_through(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> Arc:
    """The circular arc from ``p0`` through ``p1`` to ``p2`` (IFC4's IfcArcIndex)."""
    a, b = p0 - p2, p1 - p2
    axb = np.cross(a, b)
    n2 = float(np.dot(axb, axb))
    if n2 <= 1e-24 * max(float(np.dot(a, a)), float(np.dot(b, b))) ** 2:
        raise Unreadable("an IfcArcIndex through three points in a line")
    center = p2 + np.cross(np.dot(a, a) * b - np.dot(b, b) * a, axb) / (2.0 * n2)
    axis = _unit(np.cross(p1 - p0, p2 - p1), "arc axis")
    e1 = _unit(p0 - center, "arc radius")
    radius = float(np.mean([np.linalg.norm(p - center) for p in (p0, p1, p2)]))
    v = p2 - center
    end = float(np.arctan2(np.dot(np.cross(e1, v), axis), np.dot(e1, v)))
    return Arc(center, radius, axis, e1, _sweep(0.0, end))


def _indexed(c) -> list[Curve]:
    pts = [_xyz(p) for p in c.Points.CoordList]

    def point(i: int) -> np.ndarray:
        if not 1 <= i <= len(pts):
            raise Unreadable(f"an IfcIndexedPolyCurve index {i} outside its {len(pts)} points")
        return pts[i - 1]

    if not c.Segments:
        return [Line(a, b) for a, b in zip(pts, pts[1:], strict=False)]
    out: list[Curve] = []
    for seg in c.Segments:
        idx = [int(i) for i in seg.wrappedValue]
        if seg.is_a("IfcLineIndex"):
            out += [Line(point(i), point(j)) for i, j in zip(idx, idx[1:], strict=False)]
        elif seg.is_a("IfcArcIndex"):
            out.append(arc_through(point(idx[0]), point(idx[1]), point(idx[2])))
        else:
            raise Unreadable(f"an IfcIndexedPolyCurve segment {seg.is_a()}")
    return out


def _reversed(c: Curve) -> Curve:
    if c.kind == "line":
        return Line(c.end, c.start)
    return Arc(c.center, c.radius, -c.axis, (c.end - c.center) / c.radius, c.sweep)


def directrix_pieces(curve, angle_rad: float = 1.0) -> list[Curve]:
    """Centerline pieces of a directrix, in the coordinates and length unit it is written in.

    ``angle_rad``: radians per plane angle unit of the file (trimming parameters of circles use it).
    """
    kind = curve.is_a()
    if curve.is_a("IfcPolyline"):
        pts = [_xyz(p.Coordinates) for p in curve.Points]
        return [Line(a, b) for a, b in zip(pts, pts[1:], strict=False)]
    if curve.is_a("IfcIndexedPolyCurve"):
        return _indexed(curve)
    if curve.is_a("IfcTrimmedCurve"):
        return _trimmed(curve, angle_rad)
    if curve.is_a("IfcCircle"):
        origin, x, y, z = _frame(curve.Position)
        return [_arc(origin, x, y, z, curve.Radius, 0.0, _TWO_PI, True)]
    if curve.is_a("IfcCompositeCurve"):
        out: list[Curve] = []
        for seg in curve.Segments:
            if not seg.is_a("IfcCompositeCurveSegment"):
                raise Unreadable(f"an IfcCompositeCurve of {seg.is_a()} segments")
            pieces = directrix_pieces(seg.ParentCurve, angle_rad)
            out += pieces if seg.SameSense else [_reversed(p) for p in reversed(pieces)]
        return out
    raise Unreadable(f"a directrix of {kind}")


def filleted(pieces: list[Curve], radius: float) -> list[Curve]:
    """Consecutive straight pieces with each corner rounded to ``radius`` (IfcSweptDiskSolidPolygonal's
    FilletRadius): the legs cut back where the arc touches them, the arc turning in their plane."""
    if radius <= 0.0 or len(pieces) < 2:
        return pieces
    if any(c.kind != "line" for c in pieces):
        raise Unreadable("a FilletRadius on a directrix with arcs")
    starts = [c.start for c in pieces]
    ends = [c.end for c in pieces]
    arcs: list[Arc | None] = []
    for k in range(len(pieces) - 1):
        u, v = pieces[k].direction, pieces[k + 1].direction
        turn = float(np.arccos(np.clip(np.dot(u, v), -1.0, 1.0)))
        if turn < 1e-9:
            arcs.append(None)
            continue
        if turn > np.pi - 1e-9:
            raise Unreadable("a FilletRadius at a corner that turns back on itself")
        cut = radius * np.tan(turn / 2.0)
        ends[k], starts[k + 1] = pieces[k].end - u * cut, pieces[k + 1].start + v * cut
        inward = _unit(v - np.dot(v, u) * u, "fillet normal")
        center = ends[k] + radius * inward
        arcs.append(Arc(center, float(radius), _unit(np.cross(u, v), "fillet axis"), -inward, turn))
    out: list[Curve] = []
    for k in range(len(pieces)):
        leg = Line(starts[k], ends[k])
        if np.dot(leg.end - leg.start, pieces[k].direction) < -MIN_LENGTH_M:
            raise Unreadable("a FilletRadius larger than its legs allow")
        if leg.length >= MIN_LENGTH_M:
            out.append(leg)
        if k < len(arcs) and arcs[k] is not None:
            out.append(arcs[k])
    return out


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The cross product of two 3-vectors (numpy's costs more than the product for one pair)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def transformed(c: Curve, world_from_local: np.ndarray) -> Curve:
    """A piece moved by a 4x4 transform that may scale uniformly (and mirror)."""
    L, t = world_from_local[:3, :3], world_from_local[:3, 3]
    if c.kind == "line":
        return Line(L @ c.start + t, L @ c.end + t)
    u, v = L @ c.e1, L @ cross(c.axis, c.e1)
    su = float(np.sqrt(u @ u))
    e1, e2 = u / su, v / float(np.sqrt(v @ v))
    return Arc(L @ c.center + t, float(c.radius * su), cross(e1, e2), e1, float(c.sweep))


def uniform_scale(world_from_local: np.ndarray) -> float:
    """The scale of a transform whose 3x3 part is a rotation (or mirror) times one factor; Unreadable for any
    other (a non-uniform scale or a shear)."""
    L = world_from_local[:3, :3]
    gram = L.T @ L
    s2 = float(np.trace(gram)) / 3.0
    if not s2 > 0.0 or np.abs(gram - s2 * np.eye(3)).max() > 2.0 * _SCALE_TOL * s2:
        raise Unreadable("a non-uniform scale")
    return float(np.sqrt(s2))
