"""Reads reinforcing bars from an IFC model (IFC2X3, IFC4, IFC4X3) as centerlines: lines and circular arcs.

Each IfcSweptDiskSolid in the body of a selected element (IfcReinforcingBar and IfcReinforcingMesh by default)
is one bar. Its directrix becomes centerline pieces: an IfcPolyline gives lines; an IfcTrimmedCurve of an
IfcCircle (trimmed by parameter in the file's plane angle unit, or by points) or a whole IfcCircle gives an
arc; an IfcIndexedPolyCurve gives lines for its IfcLineIndex segments and arcs through the three points of its
IfcArcIndex segments; an IfcCompositeCurve gives its segments' pieces in order; an
IfcSweptDiskSolidPolygonal's FilletRadius rounds its polyline's corners into arcs. Geometry is taken in the
file's length unit through the element's IfcLocalPlacement chain and, for an element drawn by its type, the
IfcMappedItem's MappingTarget after its MappingOrigin, and is turned into metres in the model's one world
frame. The diameter is twice the solid's Radius (scaled likewise), or the element's or its type's
NominalDiameter where the solid gives none. StartParam and EndParam are taken to span the whole directrix.

Anything the reader cannot turn into a centerline (a faceted body, an unsupported curve, a non-uniform
scale) is reported with its GlobalId, never dropped silently; bad input (a missing or non-IFC file, an
unsupported schema, no bars, filters that select nothing) is one ConfigError line.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rebar_data.config import ConfigError, IfcMesh, MeshConfig
from rebar_data.geometry.curves import Arc, Curve, Line
from rebar_data.geometry.specs import Bar, IfcSource, MeshLayout, rng_streams
from rebar_data.geometry.specs import _pose as pose_matrix
from rebar_data.geometry.surface_fit import fit_surface

SCHEMAS = ("IFC2X3", "IFC4", "IFC4X3")
PSET_NAME = "RebarServo_Bar"  # what `rebar mesh --ifc` writes: BarId, Direction, Layer
MIN_LENGTH_M = 1e-9  # a shorter piece is a zero-length segment
_TWO_PI = 2.0 * np.pi
_SCALE_TOL = 1e-6
_REALISM_NOT_FOR_IFC = (
    "jitter_m",
    "jitter_normal_m",
    "bow_m",
    "missing_fraction",
    "diameters_m",
    "pose_jitter_translation_m",
    "pose_jitter_rotation_deg",
)


class Unreadable(Exception):
    """A bar whose centerline the reader cannot make (the message says why)."""


@dataclass(frozen=True)
class ReadBar:
    """One bar of the model: one IfcSweptDiskSolid of an element, its pieces in metres in the world frame."""

    global_id: str
    ifc_class: str
    item: int  # index of the solid among the element's swept disk solids
    curves: list[Curve]
    diameter_m: float
    role: str | None = None
    direction: int = -1
    layer: int = -1


@dataclass(frozen=True)
class Skipped:
    global_id: str
    ifc_class: str
    reason: str


@dataclass(frozen=True)
class IfcRead:
    """What the reader made of a file: the bars, and the selected elements it could not read."""

    path: Path
    sha256: str
    schema: str
    length_unit_m: float
    elements: int
    bars: list[ReadBar]
    skipped: list[Skipped] = field(default_factory=list)


# ---------------------------------------------------------------------------------------------- the file


def _ifcopenshell():
    try:
        import ifcopenshell
        import ifcopenshell.util.element
        import ifcopenshell.util.placement
        import ifcopenshell.util.unit
    except ImportError:
        raise ConfigError(
            "mesh.kind: ifc needs IfcOpenShell, which is not installed; accepted: install it with "
            '`pip install -e ".[ifc]"` (make setup does)'
        ) from None
    return ifcopenshell


def file_schema(path: Path) -> str:
    """The schema an IFC file declares in its header; a ConfigError for anything that is not an IFC file."""
    where = f"mesh.ifc_path {path}"
    if not path.exists():
        raise ConfigError(f"{where}: no such file; accepted: an IFC file (.ifc)")
    if path.is_dir():
        raise ConfigError(f"{where}: is a folder; accepted: an IFC file (.ifc)")
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except OSError as e:
        raise ConfigError(
            f"{where}: cannot be read ({e.strerror}); accepted: an IFC file you may read"
        ) from None
    if not head.lstrip(b"\xef\xbb\xbf \t\r\n").startswith(b"ISO-10303-21;"):
        raise ConfigError(
            f"{where}: not an IFC file (no ISO-10303-21 header); accepted: an IFC file in STEP form (.ifc), "
            "not ifcXML or ifcZIP"
        )
    m = re.search(rb"FILE_SCHEMA\s*\(\s*\(\s*'([^']*)'", head)
    if not m:
        raise ConfigError(
            f"{where}: its header names no FILE_SCHEMA; accepted: an IFC2X3, IFC4 or IFC4X3 file"
        )
    name = m.group(1).decode("ascii", "replace").strip().upper()
    for schema in SCHEMAS:
        if name == schema or (schema == "IFC4X3" and name.startswith("IFC4X3_")):
            return name
    raise ConfigError(f"{where}: schema {name} is not read; accepted: IFC2X3, IFC4 or IFC4X3")


def open_ifc(path: Path):
    """The parsed file (after :func:`file_schema` accepted its header)."""
    ifcopenshell = _ifcopenshell()
    try:
        return ifcopenshell.open(str(path))
    except Exception as e:  # the parser's errors have no common type
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ConfigError(
            f"mesh.ifc_path {path}: cannot be parsed as IFC ({first}); accepted: a valid IFC file"
        ) from None


# ---------------------------------------------------------------------------------------------- curves


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
    return origin, x, np.cross(z, x), z


def _arc(center: np.ndarray, x, y, z, radius: float, start_rad: float, sweep_rad: float, ccw: bool) -> Arc:
    e1 = np.cos(start_rad) * x + np.sin(start_rad) * y
    return Arc(center, float(radius), z if ccw else -z, e1, float(sweep_rad))


def _sweep(a0: float, a1: float) -> float:
    """The turn from angle a0 to a1 counter-clockwise, in (0, 2 pi]."""
    s = (a1 - a0) % _TWO_PI
    return _TWO_PI if s == 0.0 and a1 != a0 else s


def _trim_angle(trims, master: str, origin, x, y, angle_rad: float) -> float:
    params = [t for t in trims if t.is_a("IfcParameterValue")]
    points = [t for t in trims if t.is_a("IfcCartesianPoint")]
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
            pts = [t for t in trims if t.is_a("IfcCartesianPoint")]
            params = [t for t in trims if t.is_a("IfcParameterValue")]
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


def transformed(c: Curve, world_from_local: np.ndarray) -> Curve:
    """A piece moved by a 4x4 transform that may scale uniformly (and mirror)."""
    L, t = world_from_local[:3, :3], world_from_local[:3, 3]
    if c.kind == "line":
        return Line(L @ c.start + t, L @ c.end + t)
    u, v = L @ c.e1, L @ c.e2
    su = float(np.linalg.norm(u))
    e1, e2 = u / su, v / float(np.linalg.norm(v))
    return Arc(L @ c.center + t, float(c.radius * su), np.cross(e1, e2), e1, float(c.sweep))


def _uniform_scale(world_from_local: np.ndarray) -> float:
    sv = np.linalg.svd(world_from_local[:3, :3], compute_uv=False)
    if sv[-1] <= 0.0 or sv[0] / sv[-1] - 1.0 > _SCALE_TOL:
        raise Unreadable("a non-uniform scale")
    return float(np.mean(sv))


# ---------------------------------------------------------------------------------------------- elements


def _solids(ifcopenshell, element) -> list[tuple[object, np.ndarray]]:
    """The element's swept disk solids, each with the transform from its coordinates to the element's."""
    shape = element.Representation
    reps = list(shape.Representations) if shape else []
    body = [r for r in reps if (r.RepresentationIdentifier or "") == "Body"] or reps
    found: list[tuple[object, np.ndarray]] = []
    others: set[str] = set()

    def walk(items, m: np.ndarray, depth: int) -> None:
        for item in items:
            if item.is_a("IfcSweptDiskSolid"):
                found.append((item, m))
            elif item.is_a("IfcMappedItem") and depth < 8:
                target = item.MappingTarget
                if not target.is_a("IfcCartesianTransformationOperator3D"):
                    raise Unreadable(f"a mapped item with a {target.is_a()}")
                mapped = ifcopenshell.util.placement.get_mappeditem_transformation(item)
                walk(item.MappingSource.MappedRepresentation.Items, m @ mapped, depth + 1)
            else:
                others.add(item.is_a())

    for r in body:
        walk(r.Items, np.eye(4), 0)
    if not found:
        what = ", ".join(sorted(others)) if others else "no body"
        raise Unreadable(f"no IfcSweptDiskSolid ({what})")
    return found


def _nominal_diameter(ifcopenshell, element) -> float | None:
    for e in (element, ifcopenshell.util.element.get_type(element)):
        d = getattr(e, "NominalDiameter", None) if e is not None else None
        if d is not None:
            return float(d)
    return None


def _role(ifcopenshell, element) -> str | None:
    for e in (element, ifcopenshell.util.element.get_type(element)):
        if e is None:
            continue
        role = getattr(e, "PredefinedType", None) or getattr(e, "BarRole", None)
        if role == "USERDEFINED":
            role = getattr(e, "ObjectType", None) or getattr(e, "ElementType", None) or role
        if role and role != "NOTDEFINED":
            return str(role)
    return None


def read_element(ifcopenshell, element, *, length_m: float, angle_rad: float) -> list[ReadBar]:
    """The bars of one element (one per swept disk solid); Unreadable when it has none to read."""
    try:
        world = ifcopenshell.util.placement.get_local_placement(element.ObjectPlacement)
    except Exception:  # a grid or linear placement, or a broken chain
        kind = element.ObjectPlacement.is_a() if element.ObjectPlacement else "none"
        raise Unreadable(f"a placement the reader does not follow ({kind})") from None
    psets = ifcopenshell.util.element.get_pset(element, PSET_NAME) or {}
    role = _role(ifcopenshell, element)
    bars = []
    for k, (solid, item_m) in enumerate(_solids(ifcopenshell, element)):
        m = world @ item_m
        m = np.diag([length_m, length_m, length_m, 1.0]) @ m
        scale = _uniform_scale(m)
        radius = solid.Radius
        if radius is not None and float(radius) > 0.0:
            diameter = 2.0 * float(radius) * scale
        else:
            nominal = _nominal_diameter(ifcopenshell, element)
            diameter = (nominal if nominal is not None else float(radius or 0.0)) * length_m
        if not diameter > 0.0:
            raise Unreadable(f"a non-positive diameter ({diameter:g} m)")
        local = directrix_pieces(solid.Directrix, angle_rad)
        if local and min(c.length for c in local) * scale < MIN_LENGTH_M:
            raise Unreadable("a zero-length segment")
        if solid.is_a("IfcSweptDiskSolidPolygonal") and solid.FilletRadius:
            local = filleted(local, float(solid.FilletRadius))
        pieces = [transformed(c, m) for c in local]
        if not pieces:
            raise Unreadable("an empty directrix")
        if min(c.length for c in pieces) < MIN_LENGTH_M:
            raise Unreadable("a zero-length segment")
        bars.append(
            ReadBar(
                element.GlobalId,
                element.is_a(),
                k,
                pieces,
                diameter,
                role,
                int(psets.get("Direction", -1)),
                int(psets.get("Layer", -1)),
            )
        )
    return bars


# ---------------------------------------------------------------------------------------------- filters


def _storey_of(ifcopenshell, element):
    seen: set[int] = set()
    e = element
    while e is not None and e.id() not in seen:
        seen.add(e.id())
        if e.is_a("IfcBuildingStorey"):
            return e
        parent = ifcopenshell.util.element.get_container(e) or ifcopenshell.util.element.get_aggregate(e)
        if parent is None and hasattr(e, "Nests"):
            nests = [r.RelatingObject for r in e.Nests or []]
            parent = nests[0] if nests else None
        e = parent
    return None


def _select(ifcopenshell, f, mesh: IfcMesh, path: Path) -> list:
    where = f"mesh.ifc_path {path}"
    found: dict[int, object] = {}
    for name in mesh.ifc_classes:
        try:
            elements = f.by_type(name)
        except RuntimeError:
            raise ConfigError(
                f"mesh.ifc_classes: {name} is not a class of {f.schema}; accepted: IFC class names such as "
                "IfcReinforcingBar, IfcReinforcingMesh"
            ) from None
        found.update({e.id(): e for e in elements if e.is_a("IfcProduct")})
    if not found:
        raise ConfigError(
            f"{where}: has no {' or '.join(mesh.ifc_classes)} elements; accepted: a model with reinforcement "
            "(mesh.ifc_classes names the classes taken)"
        )
    elements = [found[k] for k in sorted(found)]
    if mesh.global_ids is not None:
        by_gid = {e.GlobalId: e for e in elements}
        missing = [g for g in mesh.global_ids if g not in by_gid]
        if missing:
            raise ConfigError(
                f"mesh.global_ids: {len(missing)} of {len(mesh.global_ids)} are not "
                f"{' or '.join(mesh.ifc_classes)} elements of {path} ({', '.join(missing[:20])}"
                f"{' ...' if len(missing) > 20 else ''}); accepted: GlobalIds of its reinforcing elements"
            )
        wanted = set(mesh.global_ids)
        elements = [e for e in elements if e.GlobalId in wanted]
    if mesh.storeys is not None:
        storeys = f.by_type("IfcBuildingStorey")
        known = {s.Name for s in storeys} | {s.GlobalId for s in storeys}
        unknown = [s for s in mesh.storeys if s not in known]
        if unknown:
            names = ", ".join(repr(s.Name) for s in storeys) or "none"
            raise ConfigError(
                f"mesh.storeys: {', '.join(map(repr, unknown))} is not a storey of {path}; accepted: the name "
                f"or GlobalId of one of its storeys ({names})"
            )
        wanted = set(mesh.storeys)
        kept = []
        for e in elements:
            storey = _storey_of(ifcopenshell, e)
            if storey is not None and (storey.Name in wanted or storey.GlobalId in wanted):
                kept.append(e)
        if not kept:
            raise ConfigError(
                f"mesh.storeys = {mesh.storeys}: no {' or '.join(mesh.ifc_classes)} elements of {path} are in "
                "them; accepted: storeys that hold reinforcement"
            )
        elements = kept
    return elements


def _in_box(c: Curve, lo: np.ndarray, hi: np.ndarray) -> bool:
    """The piece passes through the box (lines exactly; arcs every millimetre of arc)."""
    if c.kind == "line":
        d = c.end - c.start
        t0, t1 = 0.0, 1.0
        for k in range(3):
            if d[k] == 0.0:
                if not lo[k] <= c.start[k] <= hi[k]:
                    return False
                continue
            a, b = (lo[k] - c.start[k]) / d[k], (hi[k] - c.start[k]) / d[k]
            t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
        return t0 <= t1
    n = max(2, int(np.ceil(c.length / 1e-3)) + 1)
    p = c.point(np.linspace(0.0, c.length, n))
    return bool(np.any(np.all((p >= lo) & (p <= hi), axis=1)))


# ---------------------------------------------------------------------------------------------- reading


def read_ifc(mesh: IfcMesh, path: Path) -> IfcRead:
    """Read the bars ``mesh`` selects from ``path``; elements the reader cannot read are listed, not raised."""
    schema = file_schema(path)
    ifcopenshell = _ifcopenshell()
    f = open_ifc(path)
    length_m = float(ifcopenshell.util.unit.calculate_unit_scale(f, "LENGTHUNIT"))
    angle_rad = float(ifcopenshell.util.unit.calculate_unit_scale(f, "PLANEANGLEUNIT"))
    elements = _select(ifcopenshell, f, mesh, path)
    bars: list[ReadBar] = []
    skipped: list[Skipped] = []
    for e in elements:
        try:
            bars += read_element(ifcopenshell, e, length_m=length_m, angle_rad=angle_rad)
        except Unreadable as why:
            skipped.append(Skipped(e.GlobalId, e.is_a(), str(why)))
    if mesh.bbox_m is not None:
        lo, hi = np.asarray(mesh.bbox_m[0], float), np.asarray(mesh.bbox_m[1], float)
        bars = [b for b in bars if any(_in_box(c, lo, hi) for c in b.curves)]
        if not bars and not skipped:
            raise ConfigError(
                f"mesh.bbox_m = {[list(c) for c in mesh.bbox_m]}: no bar of {path} passes through it; accepted: "
                "a box (metres, the model's world frame) that bars pass through"
            )
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return IfcRead(path, digest.hexdigest(), schema, length_m, len(elements), bars, skipped)


def skipped_line(path: Path, read: IfcRead) -> str:
    """One line naming how many elements were not read, why, and their GlobalIds."""
    by_reason: dict[str, list[str]] = {}
    for s in read.skipped:
        by_reason.setdefault(s.reason, []).append(s.global_id)
    parts = [f"{reason}: {', '.join(gids)}" for reason, gids in by_reason.items()]
    n = len(read.skipped)
    return (
        f"mesh.ifc_path {path}: {n} of {read.elements} selected element{'s' if read.elements != 1 else ''} "
        f"could not be read as bars ({'; '.join(parts)}); accepted: bars drawn as IfcSweptDiskSolid along lines "
        "and circular arcs with a positive radius, or mesh.skip_unreadable: true to go on without them"
    )


def check_realism(cfg: MeshConfig) -> None:
    """The realism options that draw bars (jitter, bow, missing bars, diameters, pose jitter) have no meaning
    for bars read from a model: one line naming the first one set."""
    defaults = type(cfg.realism)()
    for name in _REALISM_NOT_FOR_IFC:
        value = getattr(cfg.realism, name)
        if value != getattr(defaults, name):
            raise ConfigError(
                f"realism.{name} = {value!r} does not apply to mesh.kind: ifc (its bars are taken as drawn); "
                f"accepted: {getattr(defaults, name)!r}, or leave it out"
            )


def _direction(bar: Bar, mat: int, fit) -> int:
    """A piece's direction as the file gives it (``rebar mesh --ifc``'s property set), else for a piece in a
    mat 0 when it runs within 45 degrees of the fitted surface's x axis and 1 across it; -1 through the
    thickness."""
    if bar.direction >= 0 or mat < 0:
        return bar.direction
    t = bar.curve.tangent(bar.curve.length / 2.0)
    return 0 if abs(float(t @ fit.world_from_surface[:3, 0])) >= np.sqrt(0.5) else 1


def ifc_layout(cfg: MeshConfig, config_dir: Path | None) -> MeshLayout:
    """The bars of ``cfg``'s IFC model as a layout: one Bar per centerline piece, posed by ``cfg.pose``, its
    ``layer`` the mat the piece lies in (:mod:`rebar_data.geometry.surface_fit`; -1 through the thickness)."""
    check_realism(cfg)
    mesh = cfg.mesh
    path = mesh.path(config_dir)
    read = read_ifc(mesh, path)
    if read.skipped and not mesh.skip_unreadable:
        raise ConfigError(skipped_line(path, read))
    if not read.bars:
        raise ConfigError(
            f"mesh.ifc_path {path}: none of its {read.elements} selected elements could be read as bars; "
            "accepted: bars drawn as IfcSweptDiskSolid along lines and circular arcs"
        )
    rngs = rng_streams(cfg.seed)
    world_from_mesh = pose_matrix(cfg, rngs["pose"])
    R, t = world_from_mesh[:3, :3], world_from_mesh[:3, 3]
    bars: list[Bar] = []
    gids, classes, pieces, roles = [], [], [], []
    for bar_id, rb in enumerate(read.bars):
        for k, c in enumerate(rb.curves):
            bars.append(Bar(bar_id, c.transformed(R, t), rb.diameter_m, rb.direction, rb.layer))
            gids.append(rb.global_id)
            classes.append(rb.ifc_class)
            pieces.append(k)
            roles.append(rb.role)
    fit = fit_surface(
        [b.curve for b in bars],
        np.array([b.diameter_m for b in bars]),
        surface=mesh.surface,
        camera_side=mesh.camera_side,
        mat_gap_m=mesh.mat_gap_m,
        top_mat=mesh.top_mat,
        need_mats=mesh.crossings == "top_mat",
        world_from_model=R,
    )
    bars = [
        replace(b, layer=int(m), direction=_direction(b, int(m), fit))
        for b, m in zip(bars, fit.piece_mat, strict=True)
    ]
    source = IfcSource(
        str(path),
        read.sha256,
        read.schema,
        read.elements,
        gids,
        classes,
        pieces,
        roles,
        [{"global_id": s.global_id, "ifc_class": s.ifc_class, "reason": s.reason} for s in read.skipped],
    )
    return MeshLayout(bars, world_from_mesh, "ifc", None, rngs, ifc=source, surface=fit)
