"""Reads reinforcing bars from an IFC model (IFC2X3, IFC4, IFC4X3) as centerlines: lines and circular arcs.

Each IfcSweptDiskSolid in the body of a selected element (IfcReinforcingBar and IfcReinforcingMesh by default)
is one bar; its directrix becomes centerline pieces (:mod:`rebar_data.geometry.ifc_curves`). Geometry is
taken in the file's length unit through the element's IfcLocalPlacement chain and, for an element drawn by
mapped items, each IfcMappedItem's MappingTarget after its MappingOrigin, and is turned into metres in the
model's one world frame. The diameter is twice the solid's Radius (scaled likewise), or the element's or its
type's NominalDiameter where the solid gives none. StartParam and EndParam are taken to span the whole
directrix. The file is taken whole or refused (:mod:`rebar_data.geometry.ifc_file`).

Vendors' exports as they are:

- A piece shorter than the model's precision (the IfcGeometricRepresentationContext's Precision, else IFC's
  default 1e-5, in the file's length unit) is dropped and its bar kept: a connector of zero length between
  two legs is no reason to lose the bar.
- A bar shorter than its own diameter (a stub of a few micrometres) is dropped and listed with its entity id
  and GlobalId (``dropped`` in mesh.json): it would give crossings where there is no bar.
- What cannot be turned into a centerline (a faceted body, an unsupported curve, a non-uniform scale) is
  reported per swept disk solid, with its entity id (``#123``), the element's GlobalId and the reason; the
  element's other solids are read. Nothing is dropped silently.
- Each IfcRepresentationMap is read once: what its items resolve to (solids, their transforms and
  directrices' pieces) is kept, so a model of thousands of mapped items costs what its bars cost.

Bad input (a missing, cut-short or non-IFC file, an unsupported schema, no bars, filters that select
nothing) is one ConfigError line.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rebar_data.config import ConfigError
from rebar_data.geometry.config import IfcMesh, MeshConfig
from rebar_data.geometry.curves import Curve
from rebar_data.geometry.ifc_curves import (
    MIN_LENGTH_M,
    Unreadable,
    cross,
    directrix_pieces,
    filleted,
    transformed,
    uniform_scale,
)
from rebar_data.geometry.ifc_file import PSET_NAME, ifcopenshell_module, open_whole
from rebar_data.geometry.specs import Bar, IfcSource, MeshLayout, rng_streams
from rebar_data.geometry.specs import _pose as pose_matrix
from rebar_data.geometry.surface_fit import fit_faces

DEFAULT_PRECISION = 1e-5  # IFC's default Precision, in the file's length unit
_MAX_MAP_DEPTH = 8
_REALISM_NOT_FOR_IFC = (
    "jitter_m",
    "jitter_normal_m",
    "bow_m",
    "missing_fraction",
    "diameters_m",
    "pose_jitter_translation_m",
    "pose_jitter_rotation_deg",
)


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
    """A solid (or a whole element) left out: its entity id, the element's GlobalId and class, and why."""

    global_id: str
    ifc_class: str
    reason: str
    entity: str = ""  # "#123": the swept disk solid, or the element when no solid of it could be looked at

    def record(self) -> dict:
        """What mesh.json lists."""
        return {
            "entity": self.entity,
            "global_id": self.global_id,
            "ifc_class": self.ifc_class,
            "reason": self.reason,
        }


@dataclass(frozen=True)
class IfcRead:
    """What the reader made of a file: the bars, what it could not read and the stubs it dropped."""

    path: Path
    sha256: str
    schema: str
    length_unit_m: float
    elements: int
    bars: list[ReadBar]
    skipped: list[Skipped] = field(default_factory=list)
    dropped: list[Skipped] = field(default_factory=list)
    precision_m: float = DEFAULT_PRECISION


# ---------------------------------------------------------------------------------------------- elements


def _xyz3(coords) -> np.ndarray:
    p = np.zeros(3)
    c = [float(x) for x in coords]
    p[: len(c)] = c
    return p


def _axes_matrix(origin: np.ndarray, z: np.ndarray, x: np.ndarray) -> np.ndarray:
    """IfcOpenShell's a2p: a 4x4 transform from an origin, a z axis and an x axis (y = z cross x; x as given,
    as IFC's writers give it square to z)."""
    x = x / np.sqrt(x @ x)
    z = z / np.sqrt(z @ z)
    y = cross(z, x)
    y = y / np.sqrt(y @ y)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, origin
    return m


def _placement_matrix(placement) -> np.ndarray:
    """An IfcAxis2Placement3D or 2D as a 4x4 transform (IfcOpenShell's get_axis2placement, for points)."""
    z = (
        _xyz3(placement.Axis.DirectionRatios)
        if getattr(placement, "Axis", None)
        else np.array([0.0, 0.0, 1.0])
    )
    x = _xyz3(placement.RefDirection.DirectionRatios) if placement.RefDirection else np.array([1.0, 0.0, 0.0])
    return _axes_matrix(_xyz3(placement.Location.Coordinates), z, x)


def _operator_matrix(op) -> np.ndarray:
    """An IfcCartesianTransformationOperator3D as a 4x4 transform (IfcOpenShell's reading of it)."""
    axis1 = _xyz3(op.Axis1.DirectionRatios) if op.Axis1 else np.array([1.0, 0.0, 0.0])
    axis2 = _xyz3(op.Axis2.DirectionRatios) if op.Axis2 else np.array([0.0, 1.0, 0.0])
    axis3 = _xyz3(op.Axis3.DirectionRatios) if op.Axis3 else np.array([0.0, 0.0, 1.0])
    m = _axes_matrix(_xyz3(op.LocalOrigin.Coordinates), axis3, axis1)
    if m[:3, 1] @ axis2 < 0.0:  # a mirror
        m[:3, 1] *= -1.0
    s1 = float(op.Scale) if op.Scale else 1.0
    scales = [s1, s1, s1]
    if op.is_a("IfcCartesianTransformationOperator3DnonUniform"):
        scales[1] = float(op.Scale2) if op.Scale2 is not None else s1
        scales[2] = float(op.Scale3) if op.Scale3 is not None else s1
    m[:3, :3] *= scales
    return m


@dataclass(frozen=True)
class _Solid:
    """A swept disk solid as a body resolves it: the transform from its coordinates to the element's."""

    solid: object
    element_from_solid: np.ndarray


class _Resolver:
    """Reads elements, each shared entity once: placements, representation maps (what their items resolve
    to) and directrices (their pieces, or why they have none) are kept by entity id."""

    def __init__(self, ifcopenshell, f, *, length_m: float, angle_rad: float, precision_m: float):
        self.ifcopenshell = ifcopenshell
        self.length_m, self.angle_rad, self.precision_m = length_m, angle_rad, precision_m
        self.types, self.psets = _relations(f)
        self._placements: dict[int, np.ndarray] = {}
        self._maps: dict[int, tuple[list[_Solid], set[str]]] = {}
        self._pieces: dict[int, tuple[list[Curve], np.ndarray] | str] = {}

    def placement(self, placement) -> np.ndarray:
        """World transform of an IfcLocalPlacement chain (file units)."""
        key = placement.id()
        if key not in self._placements:
            if not placement.is_a("IfcLocalPlacement"):
                raise Unreadable(f"a placement the reader does not follow ({placement.is_a()})")
            parent = placement.PlacementRelTo
            up = self.placement(parent) if parent is not None else np.eye(4)
            try:
                here = _placement_matrix(placement.RelativePlacement)
            except (AttributeError, TypeError, ValueError):  # a placement along an alignment, or broken
                raise Unreadable(
                    f"a placement the reader does not follow ({placement.RelativePlacement.is_a()})"
                ) from None
            self._placements[key] = up @ here
        return self._placements[key]

    def _walk(self, items, m: np.ndarray, depth: int, found: list[_Solid], others: set[str]) -> None:
        for item in items:
            if item.is_a("IfcSweptDiskSolid"):
                found.append(_Solid(item, m))
            elif item.is_a("IfcMappedItem") and depth < _MAX_MAP_DEPTH:
                target = item.MappingTarget
                if not target.is_a("IfcCartesianTransformationOperator3D"):
                    raise Unreadable(f"a mapped item with a {target.is_a()}")
                solids, inner = self._map(item.MappingSource, depth + 1)
                mm = m @ _operator_matrix(target)
                found += [_Solid(s.solid, mm @ s.element_from_solid) for s in solids]
                others |= inner
            else:
                others.add(item.is_a())

    def _map(self, source, depth: int) -> tuple[list[_Solid], set[str]]:
        """An IfcRepresentationMap's solids, each with its transform from the solid to the mapped space."""
        key = source.id()
        if key not in self._maps:
            found: list[_Solid] = []
            others: set[str] = set()
            origin = _placement_matrix(source.MappingOrigin)
            self._walk(source.MappedRepresentation.Items, origin, depth, found, others)
            self._maps[key] = (found, others)
        return self._maps[key]

    def solids(self, element) -> list[_Solid]:
        """The element's swept disk solids; Unreadable when its body has none."""
        shape = element.Representation
        reps = list(shape.Representations) if shape else []
        body = [r for r in reps if (r.RepresentationIdentifier or "") == "Body"] or reps
        found: list[_Solid] = []
        others: set[str] = set()
        for r in body:
            self._walk(r.Items, np.eye(4), 0, found, others)
        if not found:
            what = ", ".join(sorted(others)) if others else "no body"
            raise Unreadable(f"no IfcSweptDiskSolid ({what})")
        return found

    def pieces(self, solid) -> tuple[list[Curve], np.ndarray]:
        """The solid's directrix as pieces in its own coordinates (file units) and their lengths; Unreadable
        saying why not."""
        key = solid.id()
        if key not in self._pieces:
            try:
                got = directrix_pieces(solid.Directrix, self.angle_rad)
                self._pieces[key] = (got, np.array([c.length for c in got]))
            except Unreadable as why:
                self._pieces[key] = str(why)
        got = self._pieces[key]
        if isinstance(got, str):
            raise Unreadable(got)
        return got


def _relations(f) -> tuple[dict[int, object], dict[int, dict]]:
    """Every object's type, and its ``RebarServo_Bar`` properties, from one pass over the relations (not an
    inverse lookup an element)."""
    types: dict[int, object] = {}
    for rel in f.by_type("IfcRelDefinesByType"):
        for obj in rel.RelatedObjects or []:
            types[obj.id()] = rel.RelatingType
    psets: dict[int, dict] = {}
    for rel in f.by_type("IfcRelDefinesByProperties"):
        pdef = rel.RelatingPropertyDefinition
        if not (getattr(pdef, "is_a", None) and pdef.is_a("IfcPropertySet") and pdef.Name == PSET_NAME):
            continue
        props = {
            p.Name: p.NominalValue.wrappedValue
            for p in pdef.HasProperties or []
            if p.is_a("IfcPropertySingleValue") and p.NominalValue is not None
        }
        for obj in rel.RelatedObjects or []:
            psets[obj.id()] = props
    return types, psets


class _Element:
    """What an element gives every solid of it, each looked up once: its type, role and nominal diameter."""

    def __init__(self, r: _Resolver, element):
        self.e = element
        self._type = r.types.get(element.id())

    def type(self):
        return self._type

    def nominal_diameter(self) -> float | None:
        for e in (self.e, self.type()):
            d = getattr(e, "NominalDiameter", None) if e is not None else None
            if d is not None:
                return float(d)
        return None

    def role(self) -> str | None:
        for e in (self.e, self.type()):
            if e is None:
                continue
            role = getattr(e, "PredefinedType", None) or getattr(e, "BarRole", None)
            if role == "USERDEFINED":
                role = getattr(e, "ObjectType", None) or getattr(e, "ElementType", None) or role
            if role and role != "NOTDEFINED":
                return str(role)
        return None


@dataclass
class ElementRead:
    """One element's bars, the solids it could not read and the stubs it dropped."""

    bars: list[ReadBar] = field(default_factory=list)
    skipped: list[Skipped] = field(default_factory=list)
    dropped: list[Skipped] = field(default_factory=list)


def _solid_bar(r: _Resolver, el: _Element, s: _Solid, world: np.ndarray, k: int, psets: dict) -> ReadBar:
    """One solid as a bar: pieces in metres in the world, those under the precision dropped; Unreadable."""
    element = el.e
    m = np.diag([r.length_m, r.length_m, r.length_m, 1.0]) @ world @ s.element_from_solid
    scale = uniform_scale(m)
    solid = s.solid
    radius = solid.Radius
    if radius is not None and float(radius) > 0.0:
        diameter = 2.0 * float(radius) * scale
    else:
        nominal = el.nominal_diameter()
        diameter = (nominal if nominal is not None else float(radius or 0.0)) * r.length_m
    if not diameter > 0.0:
        raise Unreadable(f"a non-positive diameter ({diameter:g} m)")
    local, lengths = r.pieces(solid)
    if not local:
        raise Unreadable("an empty directrix")
    length_m = float(lengths.sum()) * scale
    if length_m < diameter:
        raise _Stub(f"a stub {length_m * 1e3:.3g} mm long, shorter than its {diameter * 1e3:.3g} mm diameter")
    if lengths.min() * scale < r.precision_m:
        local = [c for c, n in zip(local, lengths, strict=True) if n * scale >= r.precision_m]
    if not local:
        raise Unreadable("every piece shorter than the model's precision")
    if solid.is_a("IfcSweptDiskSolidPolygonal") and solid.FilletRadius:
        local = filleted(local, float(solid.FilletRadius))
    pieces = [transformed(c, m) for c in local]
    if any(c.length < MIN_LENGTH_M for c in pieces):
        raise Unreadable("a zero-length segment")
    return ReadBar(
        element.GlobalId,
        element.is_a(),
        k,
        pieces,
        diameter,
        el.role(),
        int(psets.get("Direction", -1)),
        int(psets.get("Layer", -1)),
    )


class _Stub(Exception):
    """A solid shorter than its diameter (the message says how long)."""


def read_element(r: _Resolver, element) -> ElementRead:
    """The bars of one element (one per swept disk solid), and what it could not read, solid by solid."""
    out = ElementRead()
    gid, cls = element.GlobalId, element.is_a()
    try:
        world = np.eye(4) if element.ObjectPlacement is None else r.placement(element.ObjectPlacement)
        solids = r.solids(element)
    except Unreadable as why:
        out.skipped.append(Skipped(gid, cls, str(why), f"#{element.id()}"))
        return out
    el = _Element(r, element)
    psets = r.psets.get(element.id(), {})
    for k, s in enumerate(solids):
        try:
            out.bars.append(_solid_bar(r, el, s, world, k, psets))
        except Unreadable as why:
            out.skipped.append(Skipped(gid, cls, str(why), f"#{s.solid.id()}"))
        except _Stub as why:
            out.dropped.append(Skipped(gid, cls, str(why), f"#{s.solid.id()}"))
    return out


def model_precision(f) -> float:
    """The model's precision in its length unit: its Model context's Precision, else IFC's default."""
    contexts = [
        c
        for c in f.by_type("IfcGeometricRepresentationContext")
        if not c.is_a("IfcGeometricRepresentationSubContext")
    ]
    model = [c for c in contexts if (c.ContextType or "").lower() == "model"] or contexts
    values = [float(c.Precision) for c in model if c.Precision is not None and float(c.Precision) > 0.0]
    return max(values) if values else DEFAULT_PRECISION


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
    """Read the bars ``mesh`` selects from ``path``; solids the reader cannot read are listed, not raised."""
    whole = open_whole(path)
    ifcopenshell = ifcopenshell_module()
    f = whole.model
    length_m = float(ifcopenshell.util.unit.calculate_unit_scale(f, "LENGTHUNIT"))
    angle_rad = float(ifcopenshell.util.unit.calculate_unit_scale(f, "PLANEANGLEUNIT"))
    precision_m = model_precision(f) * length_m
    elements = _select(ifcopenshell, f, mesh, path)
    resolver = _Resolver(ifcopenshell, f, length_m=length_m, angle_rad=angle_rad, precision_m=precision_m)
    bars: list[ReadBar] = []
    skipped: list[Skipped] = []
    dropped: list[Skipped] = []
    for e in elements:
        got = read_element(resolver, e)
        bars += got.bars
        skipped += got.skipped
        dropped += got.dropped
    if mesh.bbox_m is not None:
        lo, hi = np.asarray(mesh.bbox_m[0], float), np.asarray(mesh.bbox_m[1], float)
        bars = [b for b in bars if any(_in_box(c, lo, hi) for c in b.curves)]
        if not bars and not skipped:
            raise ConfigError(
                f"mesh.bbox_m = {[list(c) for c in mesh.bbox_m]}: no bar of {path} passes through it; accepted: "
                "a box (metres, the model's world frame) that bars pass through"
            )
    return IfcRead(
        path, whole.sha256, whole.schema, length_m, len(elements), bars, skipped, dropped, precision_m
    )


def reasons(items: list[Skipped], most: int = 20) -> str:
    """``reason: #id of GlobalId, ...; reason: ...``, at most ``most`` entities a reason."""
    by_reason: dict[str, list[str]] = {}
    for s in items:
        by_reason.setdefault(s.reason, []).append(f"{s.entity} of {s.global_id}" if s.entity else s.global_id)
    parts = []
    for reason, where in by_reason.items():
        more = f" and {len(where) - most} more" if len(where) > most else ""
        parts.append(f"{reason}: {', '.join(where[:most])}{more}")
    return "; ".join(parts)


def skipped_line(path: Path, read: IfcRead) -> str:
    """One line naming how many elements were not read whole, why, and each solid's entity id and GlobalId."""
    n = len({s.global_id for s in read.skipped})
    return (
        f"mesh.ifc_path {path}: {n} of {read.elements} selected element{'s' if read.elements != 1 else ''} "
        f"could not be read whole ({reasons(read.skipped)}); accepted: bars drawn as IfcSweptDiskSolid along "
        "lines and circular arcs with a positive radius, or mesh.skip_unreadable: true to go on without them"
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
        why = reasons(read.skipped + read.dropped)
        raise ConfigError(
            f"mesh.ifc_path {path}: none of its {read.elements} selected elements gave a bar"
            + (f" ({why})" if why else "")
            + "; accepted: bars drawn as IfcSweptDiskSolid along lines and circular arcs, longer than their diameter"
        )
    rngs = rng_streams(cfg.seed)
    world_from_mesh = pose_matrix(cfg, rngs["pose"])
    R, t = world_from_mesh[:3, :3], world_from_mesh[:3, 3]
    bars: list[Bar] = []
    gids, classes, pieces, roles = [], [], [], []
    in_box: list[bool] = []
    still = bool(np.array_equal(world_from_mesh, np.eye(4)))  # no pose: the pieces as read
    lo, hi = (np.asarray(c, float) for c in mesh.bbox_m) if mesh.bbox_m is not None else (None, None)
    for bar_id, rb in enumerate(read.bars):
        for k, c in enumerate(rb.curves):
            bars.append(
                Bar(bar_id, c if still else c.transformed(R, t), rb.diameter_m, rb.direction, rb.layer)
            )
            gids.append(rb.global_id)
            classes.append(rb.ifc_class)
            pieces.append(k)
            roles.append(rb.role)
            in_box.append(lo is None or _in_box(c, lo, hi))
    faces = fit_faces(
        [b.curve for b in bars],
        np.array([b.diameter_m for b in bars]),
        bar_of=np.array([b.bar_id for b in bars]),
        surface=mesh.surface,
        camera_side=mesh.camera_side,
        mat_gap_m=mesh.mat_gap_m,
        top_mat=mesh.top_mat,
        need_mats=mesh.crossings == "top_mat",
        world_from_model=R,
        preference=None if lo is None else np.array([b.curve.length for b in bars]) * np.array(in_box),
    )
    fit = faces.surface
    bars = [
        replace(b, layer=int(m), direction=_direction(b, int(m), fit))
        for b, m in zip(bars, faces.piece_mat, strict=True)
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
        [s.record() for s in read.skipped],
        [s.record() for s in read.dropped],
    )
    return MeshLayout(bars, world_from_mesh, "ifc", None, rngs, ifc=source, surface=fit, faces=faces)
