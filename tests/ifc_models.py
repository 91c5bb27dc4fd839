"""IFC models the tests write by hand with IfcOpenShell (project, site, building, storeys and elements in the
conventions of several authoring tools), and pipeline files around them. Nothing is downloaded."""

from __future__ import annotations

from pathlib import Path

import ifcopenshell
import ifcopenshell.guid
import numpy as np
import yaml

from rebar_data.geometry.build import build_rebar_mesh
from rebar_data.pipeline import load_mesh_config

ROOT = Path(__file__).resolve().parents[1]


class Model:
    """A hand-written IFC model: project, site, building, storeys, and whatever a test puts in them."""

    def __init__(self, schema: str = "IFC4", *, millimetres: bool = False, degrees: bool = False):
        self.f = f = ifcopenshell.file(schema=schema)
        self.schema = schema
        person = f.create_entity("IfcPerson", FamilyName="test")
        org = f.create_entity("IfcOrganization", Name="test")
        app = f.create_entity(
            "IfcApplication",
            ApplicationDeveloper=org,
            Version="1",
            ApplicationFullName="test",
            ApplicationIdentifier="test",
        )
        self.history = f.create_entity(
            "IfcOwnerHistory",
            OwningUser=f.create_entity("IfcPersonAndOrganization", ThePerson=person, TheOrganization=org),
            OwningApplication=app,
            ChangeAction="NOCHANGE",
            CreationDate=0,
        )
        length = f.create_entity(
            "IfcSIUnit", UnitType="LENGTHUNIT", Prefix="MILLI" if millimetres else None, Name="METRE"
        )
        radian = f.create_entity("IfcSIUnit", UnitType="PLANEANGLEUNIT", Name="RADIAN")
        angle = radian
        if degrees:
            angle = f.create_entity(
                "IfcConversionBasedUnit",
                Dimensions=f.create_entity("IfcDimensionalExponents", 0, 0, 0, 0, 0, 0, 0),
                UnitType="PLANEANGLEUNIT",
                Name="DEGREE",
                ConversionFactor=f.create_entity(
                    "IfcMeasureWithUnit",
                    ValueComponent=f.create_entity("IfcPlaneAngleMeasure", np.pi / 180.0),
                    UnitComponent=radian,
                ),
            )
        context = f.create_entity(
            "IfcGeometricRepresentationContext",
            ContextType="Model",
            CoordinateSpaceDimension=3,
            Precision=1e-5,
            WorldCoordinateSystem=self.axes(),
        )
        self.body = f.create_entity(
            "IfcGeometricRepresentationSubContext",
            ContextIdentifier="Body",
            ContextType="Model",
            ParentContext=context,
            TargetView="MODEL_VIEW",
        )
        self.project = self.rooted(
            "IfcProject",
            Name="test",
            RepresentationContexts=[context],
            UnitsInContext=f.create_entity("IfcUnitAssignment", Units=[length, angle]),
        )
        self.site_place = self.place(None)
        self.site = self.rooted(
            "IfcSite", Name="site", ObjectPlacement=self.site_place, CompositionType="ELEMENT"
        )
        self.building_place = self.place(self.site_place)
        self.building = self.rooted(
            "IfcBuilding", Name="building", ObjectPlacement=self.building_place, CompositionType="ELEMENT"
        )
        self.aggregate(self.project, [self.site])
        self.aggregate(self.site, [self.building])
        self.storeys: dict[str, tuple] = {}
        self.contained: dict[str, list] = {}

    def rooted(self, ifc_class: str, **attrs):
        return self.f.create_entity(
            ifc_class, GlobalId=ifcopenshell.guid.new(), OwnerHistory=self.history, **attrs
        )

    def aggregate(self, parent, children) -> None:
        self.rooted("IfcRelAggregates", RelatingObject=parent, RelatedObjects=children)

    def point(self, p):
        return self.f.create_entity("IfcCartesianPoint", Coordinates=[float(x) for x in p])

    def direction(self, d):
        return self.f.create_entity("IfcDirection", DirectionRatios=[float(x) for x in d])

    def axes(self, origin=(0, 0, 0), axis=None, ref=None):
        return self.f.create_entity(
            "IfcAxis2Placement3D",
            Location=self.point(origin),
            Axis=None if axis is None else self.direction(axis),
            RefDirection=None if ref is None else self.direction(ref),
        )

    def place(self, parent, origin=(0, 0, 0), axis=None, ref=None):
        return self.f.create_entity(
            "IfcLocalPlacement", PlacementRelTo=parent, RelativePlacement=self.axes(origin, axis, ref)
        )

    def storey(self, name: str = "level 0", origin=(0, 0, 0), axis=None, ref=None):
        if name not in self.storeys:
            place = self.place(self.building_place, origin, axis, ref)
            storey = self.rooted(
                "IfcBuildingStorey", Name=name, ObjectPlacement=place, CompositionType="ELEMENT"
            )
            self.aggregate(self.building, [storey])
            self.storeys[name] = (storey, place)
            self.contained[name] = []
        return self.storeys[name]

    # directrices
    def polyline(self, points):
        return self.f.create_entity("IfcPolyline", Points=[self.point(p) for p in points])

    def trimmed_circle(
        self, center, radius, t1, t2, *, axis=(0, 0, 1), ref=(1, 0, 0), sense=True, points=None
    ):
        f = self.f
        circle = f.create_entity("IfcCircle", Position=self.axes(center, axis, ref), Radius=float(radius))
        trim1 = [f.create_entity("IfcParameterValue", float(t1))]
        trim2 = [f.create_entity("IfcParameterValue", float(t2))]
        master = "PARAMETER"
        if points is not None:
            trim1, trim2, master = [self.point(points[0])], [self.point(points[1])], "CARTESIAN"
        return f.create_entity(
            "IfcTrimmedCurve",
            BasisCurve=circle,
            Trim1=trim1,
            Trim2=trim2,
            SenseAgreement=sense,
            MasterRepresentation=master,
        )

    def composite(self, curves, same_sense=None):
        same_sense = same_sense or [True] * len(curves)
        segs = [
            self.f.create_entity(
                "IfcCompositeCurveSegment",
                Transition="CONTINUOUS" if k < len(curves) - 1 else "DISCONTINUOUS",
                SameSense=s,
                ParentCurve=c,
            )
            for k, (c, s) in enumerate(zip(curves, same_sense, strict=True))
        ]
        return self.f.create_entity("IfcCompositeCurve", Segments=segs, SelfIntersect=False)

    def indexed(self, points, segments):
        f = self.f
        plist = f.create_entity("IfcCartesianPointList3D", CoordList=[[float(x) for x in p] for p in points])
        segs = [f.create_entity(kind, idx) for kind, idx in segments]
        return f.create_entity("IfcIndexedPolyCurve", Points=plist, Segments=segs, SelfIntersect=False)

    # elements
    def disk(self, directrix, radius):
        params = {"StartParam": 0.0, "EndParam": 1.0} if self.schema == "IFC2X3" else {}
        return self.f.create_entity("IfcSweptDiskSolid", Directrix=directrix, Radius=float(radius), **params)

    def shape(self, items, kind="AdvancedSweptSolid"):
        return self.f.create_entity(
            "IfcShapeRepresentation",
            ContextOfItems=self.body,
            RepresentationIdentifier="Body",
            RepresentationType=kind,
            Items=items,
        )

    def element(
        self,
        items,
        *,
        storey="level 0",
        placement=None,
        ifc_class="IfcReinforcingBar",
        diameter=None,
        kind="AdvancedSweptSolid",
    ):
        _, storey_place = self.storey(storey)
        attrs = {}
        if ifc_class == "IfcReinforcingBar":
            d = float(diameter if diameter is not None else 0.0)
            attrs = {"NominalDiameter": d, "CrossSectionArea": np.pi * d * d / 4}
            attrs |= {"BarRole": "MAIN"} if self.schema == "IFC2X3" else {"PredefinedType": "MAIN"}
        e = self.rooted(
            ifc_class,
            Name=f"{ifc_class} {len(self.f.by_type(ifc_class))}",
            ObjectPlacement=placement if placement is not None else self.place(storey_place),
            Representation=None
            if items is None
            else self.f.create_entity("IfcProductDefinitionShape", Representations=[self.shape(items, kind)]),
            **attrs,
        )
        self.contained[storey].append(e)
        return e

    def bar(self, directrix, radius, **kw):
        return self.element([self.disk(directrix, radius)], **kw)

    def write(self, path: Path) -> Path:
        for name, elements in self.contained.items():
            if elements:
                self.rooted(
                    "IfcRelContainedInSpatialStructure",
                    RelatingStructure=self.storeys[name][0],
                    RelatedElements=elements,
                )
        self.f.write(str(path))
        return path


def pipeline(tmp_path: Path, mesh: dict, *, name: str = "ifc.yaml", **top) -> Path:
    """A whole pipeline file (smoke's camera and scene) with this mesh section, no realism."""
    data = yaml.safe_load((ROOT / "pipelines/smoke.yaml").read_text())
    data.pop("realism", None)
    data["mesh"] = mesh
    data.update(top)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def read_mesh(tmp_path: Path, ifc: Path, **mesh):
    cfg = pipeline(tmp_path, {"kind": "ifc", "ifc_path": ifc.name, **mesh})
    return build_rebar_mesh(load_mesh_config(cfg), config_dir=cfg.parent)


def bar_count(rm) -> int:
    return len({b.bar_id for b in rm.bars})


# vendors' exports: the shapes users met in Tekla's, Allplan's and others' files, written here by hand


def tiny_line(m: Model, start, direction, magnitude: float, trim: float):
    """An IfcTrimmedCurve of an IfcLine whose IfcVector has ``magnitude``, trimmed by parameter 0 to ``trim``
    (Tekla writes its zero-length connectors so: a magnitude of about 5e-5 mm, trimmed by the same value)."""
    f = m.f
    line = f.create_entity(
        "IfcLine",
        Pnt=m.point(start),
        Dir=f.create_entity("IfcVector", Orientation=m.direction(direction), Magnitude=float(magnitude)),
    )
    return f.create_entity(
        "IfcTrimmedCurve",
        BasisCurve=line,
        Trim1=[f.create_entity("IfcParameterValue", 0.0)],
        Trim2=[f.create_entity("IfcParameterValue", float(trim))],
        SenseAgreement=True,
        MasterRepresentation="PARAMETER",
    )


def tekla_group(m: Model, y0: float, bars: int, *, z: float = 0.0, connector_at: int = 0):
    """One element holding ``bars`` swept disk solids (a Tekla rebar group, millimetres): L-bars along x at
    100 mm, each two legs; bar ``connector_at`` has a zero-length connector between its legs."""
    solids = []
    for k in range(bars):
        y = y0 + 100.0 * k
        leg1 = m.polyline([(0, y, z), (1000, y, z)])
        leg2 = m.polyline([(1000, y, z), (1000, y, z + 300)])
        parts = [leg1, leg2]
        if k == connector_at:
            parts = [leg1, tiny_line(m, (1000, y, z), (0, 0, 1), 4.8e-5, 4.8e-5), leg2]
        solids.append(m.disk(m.composite(parts), 6.0))
    return m.element(solids, diameter=12.0)
