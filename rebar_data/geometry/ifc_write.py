"""Writes a rebar mesh as an IFC file (IFC4, or IFC2X3 for older tools): one IfcReinforcingBar per bar.

The file holds IfcProject > IfcSite > IfcBuilding > IfcBuildingStorey (every placement the identity, units
metres and radians), and in the storey one IfcReinforcingBar per bar: its body an IfcSweptDiskSolid of the
bar's radius along its centerline, the directrix an IfcPolyline for a straight piece and an IfcTrimmedCurve
of an IfcCircle (trimmed by parameter, in radians, and by its end points) for an arc, several pieces in an
IfcCompositeCurve. Each bar carries NominalDiameter, CrossSectionArea, BarLength, its role (PredefinedType in
IFC4, BarRole in IFC2X3), ``Name`` ``bar_<id>``, ``Tag`` the bar id, and the property set ``RebarServo_Bar``
(BarId, Direction, Layer). Tie wires are left out. GlobalIds are derived from the mesh config, so the same
config gives the same file (with ``SOURCE_DATE_EPOCH`` set, byte for byte).

Bars that share a ``BarRecord.group`` are written as some authoring tools write a placement of equal bars: one
IfcReinforcingBar (the group's first bar's GlobalId and property set) whose body holds one IfcMappedItem per
bar, all of one IfcRepresentationMap (the first bar's shape), each moved by its MappingTarget. The bars of a
group must be translations of its first.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import ifcopenshell
import ifcopenshell.guid
import numpy as np

from rebar_data import __version__
from rebar_data.geometry.build import RebarMesh
from rebar_data.geometry.curves import Curve
from rebar_data.geometry.ifc_file import PSET_NAME
from rebar_data.outputs import replace_file

WRITE_SCHEMAS = ("IFC4", "IFC2X3")
ORIGINATING_SYSTEM = f"rebar mesh (rebar-data {__version__})"
_VIEWS = {"IFC4": "ViewDefinition [DesignTransferView]", "IFC2X3": "ViewDefinition [CoordinationView_V2.0]"}
_NAMESPACE = uuid.UUID("5b6f3b0e-61a4-4c0f-9d3c-2f1f3c2b7a10")
_TANGENT_TOL = 1e-9


@dataclass(frozen=True)
class BarRecord:
    """One whole bar to write: its centerline pieces in order, and what the IFC file says about it."""

    bar_id: int
    curves: list[Curve]
    diameter_m: float
    direction: int
    layer: int
    global_id: str
    role: str = "MAIN"
    group: str | None = None  # bars of one group: one element of mapped items (module doc)

    @property
    def length_m(self) -> float:
        return float(sum(c.length for c in self.curves))


def global_id(key: str) -> str:
    """A GlobalId (22 characters, IFC's base-64 GUID) fixed by ``key``."""
    return ifcopenshell.guid.compress(uuid.uuid5(_NAMESPACE, key).hex)


def bar_records(rm: RebarMesh) -> list[BarRecord]:
    """The mesh's bars, each with its pieces gathered (a bar read from IFC may have several)."""
    seed = hashlib.sha256(json.dumps(rm.config.model_dump(mode="json"), sort_keys=True).encode()).hexdigest()
    source = getattr(rm.layout, "ifc", None)
    pieces: dict[int, list[int]] = {}
    for i, b in enumerate(rm.bars):
        pieces.setdefault(b.bar_id, []).append(i)
    kept_ids: set[str] = set()
    records = []
    for bar_id, idx in pieces.items():
        first = rm.bars[idx[0]]
        gid, role = global_id(f"{seed}/bar/{bar_id}"), "MAIN"
        if source is not None:  # keep a read bar's GlobalId, unless another bar of its product took it
            gid = source.global_id[idx[0]] if source.global_id[idx[0]] not in kept_ids else gid
            role = source.role[idx[0]] or role
        kept_ids.add(gid)
        curves = [rm.bars[i].curve for i in idx]
        records.append(BarRecord(bar_id, curves, first.diameter_m, first.direction, first.layer, gid, role))
    return records


def write_ifc(
    rm: RebarMesh, path: str | Path, *, schema: str = "IFC4", project_name: str = "rebar mesh"
) -> None:
    """Write ``rm``'s bars to ``path`` (written beside it and renamed into place)."""
    model = ifc_model(
        bar_records(rm),
        schema=schema,
        project_name=project_name,
        textured=rm.config.realism.ribs,
        file_name=Path(path).name,
    )
    write_model(model, path)


def write_model(model: ifcopenshell.file, path: str | Path) -> Path:
    """Write ``model`` to ``path`` whole or not at all (a temporary file beside it, renamed into place)."""
    return replace_file(Path(path), lambda tmp: model.write(str(tmp)))


def is_mesh_ifc(path: Path) -> bool:
    """``path`` is an IFC file that `rebar mesh --ifc` wrote (its header names this program)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return head.startswith(b"ISO-10303-21;") and b"rebar mesh (rebar-data " in head


def _timestamp() -> int:
    """Seconds since the epoch: ``SOURCE_DATE_EPOCH`` when set (reproducible builds), else now."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "")
    return int(epoch) if epoch.isdigit() else int(time.time())


class _Writer:
    def __init__(self, schema: str, key: str, stamp: int):
        if schema not in WRITE_SCHEMAS:
            raise ValueError(f"schema {schema!r}; accepted: {', '.join(WRITE_SCHEMAS)}")
        self.f = ifcopenshell.file(schema=schema)
        self.key = key
        self.history = self._owner_history(stamp)
        self.origin = self._placement3d(np.zeros(3), None, None)

    def gid(self, key: str) -> str:
        return global_id(f"{self.key}/{key}")

    def create(self, ifc_class: str, key: str | None = None, **attrs):
        if key is not None:
            attrs = {"GlobalId": self.gid(key), "OwnerHistory": self.history, **attrs}
        return self.f.create_entity(ifc_class, **attrs)

    def _owner_history(self, stamp: int):
        f = self.f
        person = f.create_entity("IfcPerson", FamilyName="rebar-servo")
        org = f.create_entity("IfcOrganization", Name="rebar-servo")
        user = f.create_entity("IfcPersonAndOrganization", ThePerson=person, TheOrganization=org)
        app = f.create_entity(
            "IfcApplication",
            ApplicationDeveloper=org,
            Version=__version__,
            ApplicationFullName="rebar-data",
            ApplicationIdentifier="rebar-data",
        )
        return f.create_entity(
            "IfcOwnerHistory",
            OwningUser=user,
            OwningApplication=app,
            ChangeAction="NOCHANGE",
            CreationDate=stamp,
        )

    def point(self, p: np.ndarray):
        return self.f.create_entity("IfcCartesianPoint", Coordinates=[float(x) for x in p])

    def direction(self, d: np.ndarray):
        return self.f.create_entity("IfcDirection", DirectionRatios=[float(x) for x in d])

    def _placement3d(self, origin: np.ndarray, axis: np.ndarray | None, ref: np.ndarray | None):
        return self.f.create_entity(
            "IfcAxis2Placement3D",
            Location=self.point(origin),
            Axis=None if axis is None else self.direction(axis),
            RefDirection=None if ref is None else self.direction(ref),
        )

    def segment(self, c: Curve) -> tuple[object, float]:
        """One piece as an IFC bounded curve, and its parameter range (IFC2X3's EndParam needs it)."""
        f = self.f
        if c.kind == "line":
            return f.create_entity("IfcPolyline", Points=[self.point(c.start), self.point(c.end)]), 1.0
        circle = f.create_entity(
            "IfcCircle", Position=self._placement3d(c.center, c.axis, c.e1), Radius=float(c.radius)
        )
        trimmed = f.create_entity(
            "IfcTrimmedCurve",
            BasisCurve=circle,
            Trim1=[f.create_entity("IfcParameterValue", 0.0), self.point(c.start)],
            Trim2=[f.create_entity("IfcParameterValue", float(c.sweep)), self.point(c.end)],
            SenseAgreement=True,
            MasterRepresentation="PARAMETER",
        )
        return trimmed, float(c.sweep)

    def mapped(self, shape, context, offsets: list[np.ndarray]):
        """A body of one IfcMappedItem of ``shape`` per offset (a translation)."""
        f = self.f
        source = f.create_entity(
            "IfcRepresentationMap", MappingOrigin=self.origin, MappedRepresentation=shape
        )
        items = [
            f.create_entity(
                "IfcMappedItem",
                MappingSource=source,
                MappingTarget=f.create_entity(
                    "IfcCartesianTransformationOperator3D", LocalOrigin=self.point(t), Scale=1.0
                ),
            )
            for t in offsets
        ]
        return f.create_entity(
            "IfcShapeRepresentation",
            ContextOfItems=context,
            RepresentationIdentifier="Body",
            RepresentationType="MappedRepresentation",
            Items=items,
        )

    def directrix(self, curves: list[Curve]) -> tuple[object, float]:
        if len(curves) == 1:
            return self.segment(curves[0])
        segments, total = [], 0.0
        for i, c in enumerate(curves):
            curve, span = self.segment(c)
            total += span
            if i == len(curves) - 1:
                transition = "DISCONTINUOUS"  # an open curve's last segment
            else:
                smooth = np.dot(c.tangent(c.length), curves[i + 1].tangent(0.0)) > 1.0 - _TANGENT_TOL
                transition = "CONTSAMEGRADIENT" if smooth else "CONTINUOUS"
            segments.append(
                self.f.create_entity(
                    "IfcCompositeCurveSegment", Transition=transition, SameSense=True, ParentCurve=curve
                )
            )
        return self.f.create_entity("IfcCompositeCurve", Segments=segments, SelfIntersect=False), total


def _groups(bars: list[BarRecord]) -> list[list[BarRecord]]:
    """The bars in order, those of one ``group`` together (at its first bar's place)."""
    out: list[list[BarRecord]] = []
    index: dict[str, int] = {}
    for bar in bars:
        if bar.group is None:
            out.append([bar])
        elif bar.group in index:
            out[index[bar.group]].append(bar)
        else:
            index[bar.group] = len(out)
            out.append([bar])
    return out


def _offset(first: BarRecord, bar: BarRecord) -> np.ndarray:
    """The translation that moves ``first`` onto ``bar`` (a ValueError when none does)."""
    t = bar.curves[0].point(0.0) - first.curves[0].point(0.0)
    same = len(bar.curves) == len(first.curves) and bar.diameter_m == first.diameter_m
    for a, b in zip(first.curves, bar.curves, strict=False):
        same = same and a.kind == b.kind and abs(a.length - b.length) <= 1e-9
        ends = (a.point(0.0), a.point(a.length), b.point(0.0), b.point(b.length))
        same = (
            same
            and np.allclose(ends[0] + t, ends[2], atol=1e-9)
            and np.allclose(ends[1] + t, ends[3], atol=1e-9)
        )
    if not same:
        raise ValueError(
            f"bar {bar.bar_id} of group {bar.group!r} is not a translation of bar {first.bar_id}"
        )
    return t


def ifc_model(
    bars: list[BarRecord],
    *,
    schema: str = "IFC4",
    project_name: str = "rebar mesh",
    textured: bool = False,
    file_name: str = "mesh.ifc",
    timestamp: int | None = None,
) -> ifcopenshell.file:
    """An IFC model of ``bars`` (metres, one world frame), ready to write."""
    stamp = _timestamp() if timestamp is None else timestamp
    key = hashlib.sha256("/".join([schema, project_name, *(b.global_id for b in bars)]).encode()).hexdigest()
    w = _Writer(schema, key, stamp)
    f = w.f
    header = f.header
    header.file_description.description = (_VIEWS[schema],)
    header.file_name.name = file_name
    header.file_name.time_stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(stamp))
    header.file_name.author = ("rebar-servo",)
    header.file_name.organization = ("rebar-servo",)
    header.file_name.preprocessor_version = f"IfcOpenShell {ifcopenshell.version}"
    header.file_name.originating_system = ORIGINATING_SYSTEM
    header.file_name.authorization = "none"

    units = f.create_entity(
        "IfcUnitAssignment",
        Units=[
            f.create_entity("IfcSIUnit", UnitType="LENGTHUNIT", Name="METRE"),
            f.create_entity("IfcSIUnit", UnitType="AREAUNIT", Name="SQUARE_METRE"),
            f.create_entity("IfcSIUnit", UnitType="VOLUMEUNIT", Name="CUBIC_METRE"),
            f.create_entity("IfcSIUnit", UnitType="PLANEANGLEUNIT", Name="RADIAN"),
        ],
    )
    context = f.create_entity(
        "IfcGeometricRepresentationContext",
        ContextType="Model",
        CoordinateSpaceDimension=3,
        Precision=1e-6,
        WorldCoordinateSystem=w.origin,
    )
    body = f.create_entity(
        "IfcGeometricRepresentationSubContext",
        ContextIdentifier="Body",
        ContextType="Model",
        ParentContext=context,
        TargetView="MODEL_VIEW",
    )
    project = w.create(
        "IfcProject", "project", Name=project_name, RepresentationContexts=[context], UnitsInContext=units
    )
    site_place = f.create_entity("IfcLocalPlacement", RelativePlacement=w.origin)
    building_place = f.create_entity(
        "IfcLocalPlacement", PlacementRelTo=site_place, RelativePlacement=w.origin
    )
    storey_place = f.create_entity(
        "IfcLocalPlacement", PlacementRelTo=building_place, RelativePlacement=w.origin
    )
    site = w.create("IfcSite", "site", Name="site", ObjectPlacement=site_place, CompositionType="ELEMENT")
    building = w.create(
        "IfcBuilding", "building", Name="building", ObjectPlacement=building_place, CompositionType="ELEMENT"
    )
    storey = w.create(
        "IfcBuildingStorey",
        "storey",
        Name="rebar",
        ObjectPlacement=storey_place,
        CompositionType="ELEMENT",
        Elevation=0.0,
    )
    for parent, child, key in ((project, site, "p-s"), (site, building, "s-b"), (building, storey, "b-st")):
        w.create("IfcRelAggregates", f"aggregates/{key}", RelatingObject=parent, RelatedObjects=[child])

    surface = "TEXTURED" if textured else "PLAIN"
    products = []
    for group in _groups(bars):
        bar = group[0]
        directrix, span = w.directrix(bar.curves)
        params = {"StartParam": 0.0, "EndParam": span} if schema == "IFC2X3" else {}
        solid = f.create_entity(
            "IfcSweptDiskSolid", Directrix=directrix, Radius=bar.diameter_m / 2.0, **params
        )
        shape = f.create_entity(
            "IfcShapeRepresentation",
            ContextOfItems=body,
            RepresentationIdentifier="Body",
            RepresentationType="AdvancedSweptSolid",
            Items=[solid],
        )
        if bar.group is not None:
            shape = w.mapped(shape, body, [_offset(bar, other) for other in group])
        role = {"BarRole": bar.role} if schema == "IFC2X3" else {"PredefinedType": bar.role}
        product = f.create_entity(
            "IfcReinforcingBar",
            GlobalId=bar.global_id,
            OwnerHistory=w.history,
            Name=f"bar_{bar.bar_id:04d}",
            ObjectPlacement=f.create_entity(
                "IfcLocalPlacement", PlacementRelTo=storey_place, RelativePlacement=w.origin
            ),
            Representation=f.create_entity("IfcProductDefinitionShape", Representations=[shape]),
            Tag=str(bar.bar_id),
            NominalDiameter=bar.diameter_m,
            CrossSectionArea=float(np.pi * bar.diameter_m**2 / 4.0),
            BarLength=bar.length_m,
            BarSurface=surface,
            **role,
        )
        props = [
            f.create_entity(
                "IfcPropertySingleValue", Name=name, NominalValue=f.create_entity("IfcInteger", v)
            )
            for name, v in (("BarId", bar.bar_id), ("Direction", bar.direction), ("Layer", bar.layer))
        ]
        pset = w.create("IfcPropertySet", f"pset/{bar.global_id}", Name=PSET_NAME, HasProperties=props)
        w.create(
            "IfcRelDefinesByProperties",
            f"defines/{bar.global_id}",
            RelatedObjects=[product],
            RelatingPropertyDefinition=pset,
        )
        products.append(product)
    w.create(
        "IfcRelContainedInSpatialStructure", "contains", RelatingStructure=storey, RelatedElements=products
    )
    return f
