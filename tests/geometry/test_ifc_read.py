"""IFC in and out: `rebar mesh --ifc` writes bars a reader (ours and IfcOpenShell's kernel) reads back exactly,
and `mesh.kind: ifc` reads models written here by hand in several tools' conventions; bad input is one line.

Every model is written by the test with IfcOpenShell; nothing is downloaded.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

pytest.importorskip("ifcopenshell")
import ifcopenshell  # noqa: E402
import ifcopenshell.geom  # noqa: E402
import ifcopenshell.guid  # noqa: E402
import ifcopenshell.validate  # noqa: E402

from rebar_data.cli import main  # noqa: E402
from rebar_data.config import ConfigError  # noqa: E402
from rebar_data.geometry.build import build_rebar_mesh  # noqa: E402
from rebar_data.geometry.config import MeshConfig  # noqa: E402
from rebar_data.geometry.curves import Arc, Line  # noqa: E402
from rebar_data.geometry.ifc_curves import arc_through  # noqa: E402
from rebar_data.geometry.ifc_samples import write_shaft  # noqa: E402
from rebar_data.geometry.ifc_write import write_ifc  # noqa: E402
from tests.ifc_models import Model, bar_count, pipeline, read_mesh, tekla_group, tiny_line  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


# ---------------------------------------------------------------------------------------------- helpers


def mesh_cli(tmp_path: Path, cfg: Path, capsys, *extra: str) -> tuple[int, str, Path]:
    out = tmp_path / "out"
    code = main(["mesh", str(cfg), "--out", str(out), *extra])
    return code, capsys.readouterr().err.strip(), out


def same_crossings(a, b, tol_m: float = 1e-6) -> None:
    """The same crossings, each within ``tol_m`` (matched by bar pair, then nearest)."""
    assert len(a.crossings) == len(b.crossings)
    for c in (a.crossings, b.crossings):
        assert np.all(np.diff(c.bar_a.astype(np.int64) * 100_000 + c.bar_b) >= 0)
    np.testing.assert_array_equal(a.crossings.bar_a, b.crossings.bar_a)
    np.testing.assert_array_equal(a.crossings.bar_b, b.crossings.bar_b)
    assert np.abs(a.crossings.point - b.crossings.point).max() <= tol_m
    assert np.abs(a.crossings.gap_m - b.crossings.gap_m).max() <= tol_m


# ---------------------------------------------------------------------------------------------- IFC out


def _planar_two_mats() -> MeshConfig:
    return MeshConfig.model_validate(
        {
            "seed": 4,
            "mesh": {
                "kind": "planar",
                "width_m": 0.8,
                "height_m": 0.6,
                "spacing_x_m": 0.15,
                "spacing_y_m": 0.1,
                "layers": [{"face": "top"}, {"face": "bottom", "offset_m": [0.02, 0.0]}],
            },
            "realism": {"bow_m": 0.01},  # some bars sag: arcs in both mats
            "pose": {"translation_m": [1.0, 2.0, 0.5], "rotation_deg": [10.0, -5.0, 30.0]},
        }
    )


@pytest.mark.parametrize("schema", ["IFC4", "IFC2X3"])
def test_written_ifc_is_valid_and_ifcopenshell_draws_the_same_bars(schema, tmp_path):
    rm = build_rebar_mesh(_planar_two_mats())
    path = tmp_path / "slab.ifc"
    write_ifc(rm, path, schema=schema)
    f = ifcopenshell.open(str(path))
    log = ifcopenshell.validate.json_logger()
    ifcopenshell.validate.validate(f, log, express_rules=True)
    assert log.statements == []
    assert f.schema == schema
    for cls in ("IfcProject", "IfcSite", "IfcBuilding", "IfcBuildingStorey"):
        assert len(f.by_type(cls)) == 1
    bars = f.by_type("IfcReinforcingBar")
    assert len(bars) == len(rm.bars) and any(b.curve.kind == "arc" for b in rm.bars)
    settings = ifcopenshell.geom.settings()
    settings.set("use-world-coords", True)
    for product, bar, part in zip(bars, rm.bars, rm.parts, strict=False):
        assert product.Name == f"bar_{bar.bar_id:04d}" and product.Tag == str(bar.bar_id)
        assert product.NominalDiameter == pytest.approx(bar.diameter_m)
        assert (product.BarRole if schema == "IFC2X3" else product.PredefinedType) == "MAIN"
        solid = product.Representation.Representations[0].Items[0]
        assert solid.is_a("IfcSweptDiskSolid")
        assert solid.Directrix.is_a("IfcTrimmedCurve" if bar.curve.kind == "arc" else "IfcPolyline")
        verts = np.asarray(ifcopenshell.geom.create_shape(settings, product).geometry.verts).reshape(-1, 3)
        # IfcOpenShell's kernel and our tube agree on the bar's extent (ours is a 16-sided circumscribed tube)
        assert np.abs(verts.min(0) - part.mesh.bounds[0]).max() < 1e-3
        assert np.abs(verts.max(0) - part.mesh.bounds[1]).max() < 1e-3


def test_written_ifc_is_the_same_file_for_the_same_config(tmp_path, monkeypatch):
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    rm = build_rebar_mesh(_planar_two_mats())
    write_ifc(rm, tmp_path / "a.ifc")
    write_ifc(build_rebar_mesh(_planar_two_mats()), tmp_path / "b.ifc")
    a, b = (tmp_path / "a.ifc").read_text(), (tmp_path / "b.ifc").read_text()
    assert a.replace("'a.ifc'", "'b.ifc'") == b


def test_mesh_ifc_flag_writes_and_replaces_only_its_own_file(tmp_path, capsys):
    cfg = str(ROOT / "pipelines/smoke.yaml")
    ifc = tmp_path / "smoke.ifc"
    assert main(["mesh", cfg, "--out", str(tmp_path / "m"), "--ifc", str(ifc)]) == 0
    assert ifc.read_bytes().startswith(b"ISO-10303-21;")
    assert main(["mesh", cfg, "--out", str(tmp_path / "m"), "--ifc", str(ifc)]) == 0  # its own: replaced
    capsys.readouterr()
    other = tmp_path / "other.ifc"
    other.write_text("ISO-10303-21;\nsomeone else's model\n")
    for bad, words in (
        (other, "did not write"),
        (tmp_path / "model.txt", "not a .ifc file name"),
        (tmp_path / "m2" / "in-out.ifc", "lies in --out"),
    ):
        out = tmp_path / "m2"
        assert main(["mesh", cfg, "--out", str(out), "--ifc", str(bad)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and words in err, err
        assert not out.exists()
    assert other.read_text().endswith("someone else's model\n")


# ---------------------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize(
    "source",
    [ROOT / "pipelines/paper-tunnel.yaml", "planar-two-mats"],
    ids=["paper-tunnel", "planar-two-mats"],
)
def test_round_trip_through_ifc_keeps_bars_and_crossings(source, tmp_path, capsys):
    if source == "planar-two-mats":
        cfg = _planar_two_mats()
        source = pipeline(tmp_path, cfg.mesh.model_dump(mode="json"), name="slab.yaml", seed=cfg.seed)
        data = yaml.safe_load(source.read_text())
        data["realism"] = cfg.realism.model_dump(mode="json")
        data["pose"] = cfg.pose.model_dump(mode="json")
        source.write_text(yaml.safe_dump(data, sort_keys=False))
    two_mats = "tunnel" not in str(source)
    ifc = tmp_path / "model.ifc"
    assert main(["mesh", str(source), "--out", str(tmp_path / "a"), "--ifc", str(ifc)]) == 0
    # every crossing of both mats; the default keeps the top mat's (checked below)
    cfg = pipeline(tmp_path, {"kind": "ifc", "ifc_path": "model.ifc", "crossings": "all"})
    assert main(["mesh", str(cfg), "--out", str(tmp_path / "b")]) == 0
    capsys.readouterr()

    a = {k: pq.read_table(tmp_path / "a" / f"{k}.parquet").to_pandas() for k in ("bars", "crossings")}
    b = {k: pq.read_table(tmp_path / "b" / f"{k}.parquet").to_pandas() for k in ("bars", "crossings")}
    assert len(a["bars"]) == len(b["bars"]) and b["bars"].bar_id.is_unique
    assert list(b["bars"].columns[: len(a["bars"].columns)]) == list(a["bars"].columns)
    for col in ("kind", "direction", "layer"):
        assert (a["bars"][col] == b["bars"][col]).all()
    assert np.abs(a["bars"].diameter_m - b["bars"].diameter_m).max() < 1e-12
    assert len(a["crossings"]) == len(b["crossings"])
    if "tunnel" in str(source):
        assert len(b["crossings"]) == 720
    for col in ("bar_a", "bar_b", "layer"):
        assert (a["crossings"][col] == b["crossings"][col]).all()
    for col in ("x", "y", "z", "x_a", "y_a", "z_a", "x_b", "y_b", "z_b", "gap_m"):
        assert np.abs(a["crossings"][col] - b["crossings"][col]).max() <= 1e-6, col
    # the crossings name both bars' GlobalIds, the ones the IFC file gives them
    f = ifcopenshell.open(str(ifc))
    gid = {int(p.Tag): p.GlobalId for p in f.by_type("IfcReinforcingBar")}
    assert (b["crossings"].global_id_a == b["crossings"].bar_a.map(gid)).all()
    assert (b["crossings"].global_id_b == b["crossings"].bar_b.map(gid)).all()
    assert (b["bars"].global_id == b["bars"].bar_id.map(gid)).all()
    summary = json.loads((tmp_path / "b/mesh.json").read_text())
    assert summary["bars"] == len(a["bars"]) and summary["ifc"]["schema"] == "IFC4"
    assert summary["ifc"]["skipped"] == [] and len(summary["ifc"]["sha256"]) == 64
    # the fitted surface: a cylinder for the tunnel, a plane for the slab; its mats are the source's layers
    surface = summary["surface"]
    assert surface["kind"] == ("plane" if two_mats else "cylinder")
    assert len(surface["mats"]) == (2 if two_mats else 1) and surface["pieces_through"] == 0
    top = read_mesh(tmp_path, ifc, crossings="top_mat")
    in_top = a["crossings"][a["crossings"].layer == 0]
    assert len(top.crossings) == len(in_top) == (25 if two_mats else 720)
    assert np.abs(top.crossings.point - in_top[["x", "y", "z"]].to_numpy()).max() <= 1e-6


# ---------------------------------------------------------------------------------------------- IFC in


def test_a_bent_bar_of_lines_and_arcs_is_one_bar_that_crosses_others_exactly(tmp_path):
    """IFC4's IfcIndexedPolyCurve: straight, a quarter bend (IfcArcIndex), straight; 16 mm bar, 12 mm bars."""
    m = Model("IFC4")
    r = 0.1
    pts = [
        (0, 0, 0),
        (1, 0, 0),
        (1 + r * np.sqrt(0.5), r - r * np.sqrt(0.5), 0),
        (1 + r, r, 0),
        (1 + r, 1, 0),
    ]
    m.bar(
        m.indexed(pts, [("IfcLineIndex", [1, 2]), ("IfcArcIndex", [2, 3, 4]), ("IfcLineIndex", [4, 5])]),
        0.008,
    )
    m.bar(m.polyline([(0.5, -0.5, 0.014), (0.5, 0.5, 0.014)]), 0.006)  # on top of the first leg, touching
    mid = np.array(pts[2], float)
    m.bar(m.polyline([mid - (0, 0, 0.3), mid + (0, 0, 0.3)]), 0.006)  # through the bend, upright
    m.bar(m.polyline([(0.8, 0.6, -0.014), (1.4, 0.6, -0.014)]), 0.006)  # beneath the last leg
    m.bar(m.polyline([(0.2, 0.014, 0.0), (0.8, 0.014, 0.0)]), 0.006)  # beside the first leg, touching: lapped
    rm = read_mesh(tmp_path, m.write(tmp_path / "bent.ifc"), crossing_tolerance_m=0.001)
    assert bar_count(rm) == 5 and len(rm.bars) == 7
    bent = [b for b in rm.bars if b.bar_id == 0]
    assert [b.curve.kind for b in bent] == ["line", "arc", "line"]
    arc = bent[1].curve
    np.testing.assert_allclose(arc.center, [1.0, r, 0.0], atol=1e-12)
    assert arc.radius == pytest.approx(r, abs=1e-12) and arc.sweep == pytest.approx(np.pi / 2, abs=1e-12)
    assert rm.layout.ifc.piece[:3] == [0, 1, 2]
    c = rm.crossings
    assert list(zip(c.bar_a.tolist(), c.bar_b.tolist(), strict=True)) == [(0, 1), (0, 2), (0, 3)]
    np.testing.assert_allclose(c.point[0], [0.5, 0.0, 0.007], atol=1e-12)
    np.testing.assert_allclose(c.point[1], mid, atol=1e-9)  # on the arc, found exactly
    np.testing.assert_allclose(c.point[2], [1 + r, 0.6, -0.007], atol=1e-12)
    assert c.piece_a.tolist() == [0, 1, 2]
    assert np.abs(c.gap_m[[0, 2]]).max() < 1e-12 and c.gap_m[1] == pytest.approx(-0.014)
    np.testing.assert_allclose(np.abs(c.normal[:, 2])[[0, 2]], 1.0)
    assert rm.mesh.is_watertight and set(np.unique(rm.triangle_bar_id)) == {0, 1, 2, 3, 4}

    # written back, the bent bar is one IfcReinforcingBar with an IfcCompositeCurve, read the same again
    write_ifc(rm, tmp_path / "again.ifc")
    f = ifcopenshell.open(str(tmp_path / "again.ifc"))
    directrix = f.by_type("IfcReinforcingBar")[0].Representation.Representations[0].Items[0].Directrix
    assert directrix.is_a("IfcCompositeCurve") and len(directrix.Segments) == 3
    again = read_mesh(tmp_path, tmp_path / "again.ifc", crossing_tolerance_m=0.001)
    same_crossings(rm, again, 1e-12)


def test_a_polygonal_swept_disk_rounds_its_corners_by_the_fillet_radius(tmp_path):
    """IFC4's IfcSweptDiskSolidPolygonal: a polyline whose corners are bends of FilletRadius."""
    m = Model("IFC4")
    solid = m.f.create_entity(
        "IfcSweptDiskSolidPolygonal",
        Directrix=m.polyline([(0, 0, 0), (1, 0, 0), (1, 1, 0), (1, 1, 1)]),
        Radius=0.006,
        FilletRadius=0.1,
    )
    m.element([solid], diameter=0.012)
    rm = read_mesh(tmp_path, m.write(tmp_path / "polygonal.ifc"))
    kinds = [b.curve.kind for b in rm.bars]
    assert kinds == ["line", "arc", "line", "arc", "line"] and bar_count(rm) == 1
    np.testing.assert_allclose(rm.bars[0].curve.end, [0.9, 0, 0], atol=1e-12)
    first, second = rm.bars[1].curve, rm.bars[3].curve
    np.testing.assert_allclose(first.center, [0.9, 0.1, 0], atol=1e-12)
    np.testing.assert_allclose(second.center, [1.0, 0.9, 0.1], atol=1e-12)
    for arc in (first, second):
        assert arc.radius == pytest.approx(0.1) and arc.sweep == pytest.approx(np.pi / 2)
    for a, b in zip(rm.bars, rm.bars[1:], strict=False):  # one smooth centerline
        np.testing.assert_allclose(a.curve.end, b.curve.start, atol=1e-12)
        np.testing.assert_allclose(a.curve.tangent(a.curve.length), b.curve.tangent(0.0), atol=1e-12)
    assert len(rm.parts) == 5 and rm.mesh.is_watertight  # smooth joints: no balls

    # without the fillet the corners are sharp: three legs, and a ball in each corner
    m = Model("IFC4")
    m.bar(m.polyline([(0, 0, 0), (1, 0, 0), (1, 1, 0), (1, 1, 1)]), 0.006)
    rm = read_mesh(tmp_path, m.write(tmp_path / "sharp.ifc"))
    assert [b.curve.kind for b in rm.bars] == ["line"] * 3 and len(rm.parts) == 5
    assert rm.mesh.is_watertight and set(rm.triangle_bar_id.tolist()) == {0}


def _stirrup(m: Model, x: float, w: float, h: float, rb: float, *, reverse: bool = False):
    """A closed rectangular stirrup in the plane x = const, corners bent to radius ``rb`` (centerline):
    four IfcPolyline legs and four IfcTrimmedCurve quarter circles (parameters in degrees)."""
    cy, cz = w / 2 - rb, h / 2 - rb
    corners = [(cy, cz, 0), (-cy, cz, 90), (-cy, -cz, 180), (cy, -cz, 270)]  # arc centres, start angle
    # the circle's frame: axis +x, ref +y, so angle 0 is +y and 90 is +z
    curves = []
    for k, (yc, zc, a0) in enumerate(corners):
        curves.append(m.trimmed_circle((x, yc, zc), rb, a0, a0 + 90, axis=(1, 0, 0), ref=(0, 1, 0)))
        y1, z1 = yc + rb * np.cos(np.radians(a0 + 90)), zc + rb * np.sin(np.radians(a0 + 90))
        nyc, nzc, na0 = corners[(k + 1) % 4]
        y2, z2 = nyc + rb * np.cos(np.radians(na0)), nzc + rb * np.sin(np.radians(na0))
        curves.append(m.polyline([(x, y1, z1), (x, y2, z2)]))
    if not reverse:
        return m.composite(curves)
    # the same loop written backwards: segments reversed, each with SameSense false
    return m.composite(list(reversed(curves)), [False] * len(curves))


def test_a_stirrup_cage_crosses_its_corner_bars_in_the_bends(tmp_path):
    """IFC2X3 in degrees: closed stirrups of IfcCompositeCurve (legs and bends) around four corner bars."""
    m = Model("IFC2X3", degrees=True)
    w, h, rb, rs, rl = 0.3, 0.4, 0.024, 0.005, 0.008
    xs = [0.1, 0.3, 0.5, 0.7, 0.9]
    for k, x in enumerate(xs):
        m.bar(_stirrup(m, x, w, h, rb, reverse=k == 2), rs, diameter=2 * rs)
    rho = rb - (rs + rl)  # corner bar axis from the bend's centre, along the diagonal: touching the bend
    diag = np.sqrt(0.5)
    corner_axes = []
    for sy, sz in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        y, z = sy * (w / 2 - rb + rho * diag), sz * (h / 2 - rb + rho * diag)
        corner_axes.append((y, z))
        m.bar(m.polyline([(0.0, y, z), (1.0, y, z)]), rl, diameter=2 * rl)
    rm = read_mesh(tmp_path, m.write(tmp_path / "cage.ifc"), crossing_tolerance_m=0.001)
    assert rm.layout.ifc.schema == "IFC2X3"
    assert bar_count(rm) == len(xs) + 4 and len(rm.bars) == 8 * len(xs) + 4
    c = rm.crossings
    assert len(c) == 4 * len(xs)
    assert set(c.bar_b.tolist()) == set(
        range(len(xs), len(xs) + 4)
    )  # stirrup x corner bar, never a bar with itself
    assert np.all(c.bar_a < len(xs))
    assert np.abs(c.gap_m).max() < 1e-12  # they touch
    for y, z in corner_axes:  # each corner bar meets every stirrup in its bend, halfway between the axes
        on_bar = np.isclose(c.point[:, 1], y + np.sign(y) * (rs + rl) / 2 * diag, atol=1e-9) & np.isclose(
            c.point[:, 2], z + np.sign(z) * (rs + rl) / 2 * diag, atol=1e-9
        )
        assert sorted(c.point[on_bar, 0].round(9)) == xs
    assert rm.mesh.is_watertight


def test_authoring_tool_conventions_millimetres_nested_placements_and_mapped_types(tmp_path):
    """A model as authoring tools export it: millimetres, site > building > storey > assembly placements,
    the bar's shape once on its IfcReinforcingBarType (a representation map with an offset origin) and each
    occurrence an IfcMappedItem with its own MappingTarget. Checked against IfcOpenShell's own kernel."""
    m = Model("IFC4", millimetres=True)
    # site 1 km east, turned 90 degrees about z; storey 3 m up
    m.site.ObjectPlacement.RelativePlacement = m.axes((1_000_000, 0, 0), (0, 0, 1), (0, 1, 0))
    storey, storey_place = m.storey("level 1", origin=(0, 0, 3000))
    assembly_place = m.place(storey_place, (500, 200, 0), (0, 0, 1), (0, 1, 0))  # turned 90 again
    shape = m.shape([m.disk(m.polyline([(0, 0, 0), (2000, 0, 0)]), 6.0)])
    rep_map = m.f.create_entity(
        "IfcRepresentationMap", MappingOrigin=m.axes((100, 0, 0)), MappedRepresentation=shape
    )
    bar_type = m.rooted(
        "IfcReinforcingBarType",
        Name="H12",
        RepresentationMaps=[rep_map],
        PredefinedType="MAIN",
        NominalDiameter=12.0,
        BarLength=2000.0,
    )
    occurrences = []
    for k in range(4):
        target = m.f.create_entity(
            "IfcCartesianTransformationOperator3D",
            Axis1=m.direction((1, 0, 0)),
            Axis2=m.direction((0, 1, 0)),
            LocalOrigin=m.point((0, 150 * k, 0)),
            Scale=1.0,
            Axis3=m.direction((0, 0, 1)),
        )
        mapped = m.f.create_entity("IfcMappedItem", MappingSource=rep_map, MappingTarget=target)
        occurrence = m.element(
            [mapped], storey="level 1", placement=m.place(assembly_place), kind="MappedRepresentation"
        )
        occurrence.PredefinedType = "NOTDEFINED"  # the role is the type's
        occurrences.append(occurrence)
    m.rooted("IfcRelDefinesByType", RelatedObjects=occurrences, RelatingType=bar_type)
    # a cross bar drawn directly, in the assembly's frame: along y at x = 1000, beneath the mapped bars
    cross = m.bar(
        m.polyline([(1100, -100, -12), (1100, 600, -12)]),
        6.0,
        storey="level 1",
        placement=m.place(assembly_place),
    )
    rm = read_mesh(tmp_path, m.write(tmp_path / "tool.ifc"), crossing_tolerance_m=0.0005)

    assert bar_count(rm) == 5 and all(b.diameter_m == pytest.approx(0.012) for b in rm.bars)
    # by hand: the two 90 degree turns make the assembly's x point along world -x, its y along -y; the map's
    # origin moves the bar 100 mm along its x, the target 150 mm a bar along its y
    for k, b in enumerate(rm.bars[:4]):
        np.testing.assert_allclose(b.curve.start, [1000 - 0.3, 0.5 - 0.15 * k, 3.0], atol=1e-9)
        np.testing.assert_allclose(b.curve.end, [1000 - 2.3, 0.5 - 0.15 * k, 3.0], atol=1e-9)
    assert len(rm.crossings) == 4 and np.allclose(rm.crossings.point[:, 0], 1000 - 1.3, atol=1e-9)
    np.testing.assert_allclose(rm.crossings.point[:, 2], 3.0 - 0.006, atol=1e-9)
    assert rm.layout.ifc.role[:4] == ["MAIN"] * 4  # from the type
    # IfcOpenShell's geometry kernel places the same bars
    settings = ifcopenshell.geom.settings()
    settings.set("use-world-coords", True)
    f = ifcopenshell.open(str(tmp_path / "tool.ifc"))
    for product, bar, part in zip([*occurrences, cross], rm.bars, rm.parts, strict=True):
        verts = np.asarray(
            ifcopenshell.geom.create_shape(settings, f.by_guid(product.GlobalId)).geometry.verts
        )
        verts = verts.reshape(-1, 3)
        assert np.abs(verts.min(0) - part.mesh.bounds[0]).max() < 1e-3, bar.bar_id
        assert np.abs(verts.max(0) - part.mesh.bounds[1]).max() < 1e-3, bar.bar_id


@pytest.mark.parametrize("schema", ["IFC2X3", "IFC4", "IFC4X3"])
def test_every_accepted_schema_reads_the_same_two_bars(schema, tmp_path):
    m = Model(schema)
    m.bar(m.polyline([(0, 0, 0), (1, 0, 0)]), 0.006, diameter=0.012)
    m.bar(m.trimmed_circle((0.5, 0, -0.5), 0.512, 0.5, np.pi - 0.5, axis=(1, 0, 0), ref=(0, 1, 0)), 0.006)
    rm = read_mesh(tmp_path, m.write(tmp_path / f"{schema}.ifc"))
    assert rm.layout.ifc.schema.startswith(schema) and bar_count(rm) == 2
    assert len(rm.crossings) == 1 and rm.crossings.gap_m[0] == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(rm.crossings.point[0], [0.5, 0.0, 0.006], atol=1e-12)


def test_filters_by_class_storey_global_id_and_box(tmp_path):
    m = Model("IFC4")
    lower = [m.bar(m.polyline([(0, y, 0), (1, y, 0)]), 0.006, storey="ground") for y in (0.1, 0.2)]
    upper = [m.bar(m.polyline([(0, y, 3), (1, y, 3)]), 0.006, storey="first") for y in (0.1, 0.2, 0.3)]
    mesh_el = m.element(
        [m.disk(m.polyline([(x, 0, 3.012), (x, 0.4, 3.012)]), 0.006) for x in (0.25, 0.5, 0.75)],
        storey="first",
        ifc_class="IfcReinforcingMesh",
    )
    path = m.write(tmp_path / "two-storeys.ifc")
    everything = read_mesh(tmp_path, path)
    assert bar_count(everything) == 8 and len(everything.crossings) == 9  # 3 mesh wires x 3 upper bars
    assert set(everything.layout.ifc.ifc_class) == {"IfcReinforcingBar", "IfcReinforcingMesh"}
    assert (
        read_mesh(tmp_path, path, ifc_classes=["IfcReinforcingMesh"]).layout.ifc.global_id
        == [mesh_el.GlobalId] * 3
    )
    ground = read_mesh(tmp_path, path, storeys=["ground"])
    assert ground.layout.ifc.global_id == [e.GlobalId for e in lower]
    storey_gid = m.storeys["first"][0].GlobalId
    assert bar_count(read_mesh(tmp_path, path, storeys=[storey_gid])) == 6
    picked = read_mesh(tmp_path, path, global_ids=[upper[0].GlobalId, mesh_el.GlobalId])
    assert bar_count(picked) == 4 and len(picked.crossings) == 3
    boxed = read_mesh(tmp_path, path, bbox_m=[[0.4, -1, 2], [0.6, 0.15, 4]])  # one wire, one upper bar
    assert bar_count(boxed) == 2 and len(boxed.crossings) == 1


def test_skip_unreadable_goes_on_and_lists_what_it_left_out(tmp_path, capsys):
    m = Model("IFC4")
    m.bar(m.polyline([(0, 0, 0), (1, 0, 0)]), 0.006)
    m.bar(m.polyline([(0.5, -0.5, 0.012), (0.5, 0.5, 0.012)]), 0.006)
    brep = _faceted_bar(m)
    path = m.write(tmp_path / "with-brep.ifc")
    cfg = pipeline(tmp_path, {"kind": "ifc", "ifc_path": path.name})
    code, err, out = mesh_cli(tmp_path, cfg, capsys)
    assert code == 2 and err.count("\n") == 0 and not out.exists()
    assert "1 of 3 selected elements could not be read whole" in err and brep.GlobalId in err
    assert "IfcFacetedBrep" in err and "skip_unreadable" in err
    cfg = pipeline(tmp_path, {"kind": "ifc", "ifc_path": path.name, "skip_unreadable": True})
    code, err, out = mesh_cli(tmp_path, cfg, capsys)
    assert code == 0 and "1 IFC element not read whole" in err
    summary = json.loads((out / "mesh.json").read_text())
    assert summary["bars"] == 2 and summary["crossings"] == 1
    assert summary["ifc"]["skipped"] == [
        {
            "entity": f"#{brep.id()}",
            "global_id": brep.GlobalId,
            "ifc_class": "IfcReinforcingBar",
            "reason": "no IfcSweptDiskSolid (IfcFacetedBrep)",
        }
    ]


def _faceted_bar(m: Model):
    """A bar drawn as a faceted box (as some tools export bent bars): no centerline to read."""
    f = m.f
    corners = [m.point((x, y, z)) for x in (0, 1) for y in (0, 0.01) for z in (0, 0.01)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    shell = f.create_entity(
        "IfcClosedShell",
        CfsFaces=[
            f.create_entity(
                "IfcFace",
                Bounds=[
                    f.create_entity(
                        "IfcFaceOuterBound",
                        Bound=f.create_entity("IfcPolyLoop", Polygon=[corners[i] for i in face]),
                        Orientation=True,
                    )
                ],
            )
            for face in faces
        ],
    )
    return m.element([f.create_entity("IfcFacetedBrep", Outer=shell)], diameter=0.01, kind="Brep")


# ---------------------------------------------------------------------------------------------- vendors' exports


def test_a_zero_length_connector_is_dropped_and_its_bars_kept(tmp_path, capsys):
    """Tekla (IFC2X3, millimetres, Precision 1e-5 mm): a group of 5 L-bars and one of 23, each with an IfcLine
    connector between one bar's legs (magnitude 4.8e-5 mm, trimmed by the same: 2.3e-9 mm long); a bar with a
    repeated point. The connectors and the repeated point are dropped, every bar kept."""
    m = Model("IFC2X3", millimetres=True)
    five = tekla_group(m, 0.0, 5)
    tekla_group(m, 1000.0, 23, connector_at=11)
    m.bar(m.polyline([(0, 3400, 0), (500, 3400, 0), (500, 3400, 0), (1000, 3400, 0)]), 6.0, diameter=12.0)
    m.bar(m.polyline([(500, -100, 12), (500, 3500, 12)]), 6.0, diameter=12.0)  # across all, on top
    path = m.write(tmp_path / "tekla.ifc")
    code, err, out = mesh_cli(tmp_path, pipeline(tmp_path, {"kind": "ifc", "ifc_path": path.name}), capsys)
    assert code == 0, err
    summary = json.loads((out / "mesh.json").read_text())
    assert summary["bars"] == 30 and summary["crossings"] == 29
    assert summary["ifc"]["skipped"] == [] and summary["ifc"]["dropped"] == []
    bars = pq.read_table(out / "bars.parquet").to_pandas()
    first = bars[bars.bar_id == 0]  # the connector's bar: its two legs, joined
    assert first.kind.tolist() == ["line", "line"] and set(first.global_id) == {five.GlobalId}
    assert first.length_m.tolist() == pytest.approx([1.0, 0.3], abs=1e-9)
    assert (bars.bar_id == 28).sum() == 2  # the repeated point's zero-length piece dropped


def test_an_unreadable_solid_is_reported_alone_with_its_entity_id(tmp_path, capsys):
    """One element of 24 swept disk solids, one along an IfcEllipse: that solid is named (#id, GlobalId,
    reason); with skip_unreadable the other 23 are read."""
    m = Model("IFC4")
    good = [m.disk(m.polyline([(0, 0.1 * k, 0), (1, 0.1 * k, 0)]), 0.006) for k in range(23)]
    ellipse = m.f.create_entity("IfcEllipse", Position=m.axes(), SemiAxis1=0.5, SemiAxis2=0.2)
    bad = m.disk(ellipse, 0.006)
    group = m.element(good[:11] + [bad] + good[11:], diameter=0.012)
    m.bar(m.polyline([(0.5, -0.1, 0.012), (0.5, 2.4, 0.012)]), 0.006, diameter=0.012)
    path = m.write(tmp_path / "group.ifc")
    code, err, out = mesh_cli(tmp_path, pipeline(tmp_path, {"kind": "ifc", "ifc_path": path.name}), capsys)
    assert code == 2 and err.count("\n") == 0 and not out.exists()
    assert f"a directrix of IfcEllipse: #{bad.id()} of {group.GlobalId}" in err, err
    cfg = pipeline(tmp_path, {"kind": "ifc", "ifc_path": path.name, "skip_unreadable": True})
    code, err, out = mesh_cli(tmp_path, cfg, capsys)
    assert code == 0, err
    summary = json.loads((out / "mesh.json").read_text())
    assert summary["bars"] == 24 and summary["crossings"] == 23
    assert summary["ifc"]["skipped"] == [
        {
            "entity": f"#{bad.id()}",
            "global_id": group.GlobalId,
            "ifc_class": "IfcReinforcingBar",
            "reason": "a directrix of IfcEllipse",
        }
    ]


def test_a_stub_shorter_than_its_diameter_is_dropped_and_listed(tmp_path, capsys):
    """Tekla: a 12 mm solid with EndParam 0.028 mm, lying on a bar 150 mm from its one real crossing."""
    m = Model("IFC2X3", millimetres=True)
    m.bar(m.polyline([(-200, 0, 0), (600, 0, 0)]), 6.0, diameter=12.0)
    m.bar(m.polyline([(0, -200, 12), (0, 400, 12)]), 6.0, diameter=12.0)
    solid = m.f.create_entity(
        "IfcSweptDiskSolid",
        Directrix=tiny_line(m, (150, 0, 12), (0, 1, 0), 1.0, 0.028),
        Radius=6.0,
        StartParam=0.0,
        EndParam=0.028,
    )
    stub = m.element([solid], diameter=12.0)
    path = m.write(tmp_path / "stub.ifc")
    code, err, out = mesh_cli(tmp_path, pipeline(tmp_path, {"kind": "ifc", "ifc_path": path.name}), capsys)
    assert code == 0 and "1 stub shorter than its diameter dropped" in err, err
    summary = json.loads((out / "mesh.json").read_text())
    assert summary["bars"] == 2 and summary["crossings"] == 1  # the real crossing only
    assert summary["ifc"]["dropped"] == [
        {
            "entity": f"#{solid.id()}",
            "global_id": stub.GlobalId,
            "ifc_class": "IfcReinforcingBar",
            "reason": "a stub 0.028 mm long, shorter than its 12 mm diameter",
        }
    ]
    assert summary["ifc"]["skipped"] == []


def test_mapped_items_read_each_representation_map_once(tmp_path, monkeypatch):
    """Allplan: a lift shaft whose bars are placements of mapped items (6 IfcRepresentationMaps, 52 items).
    Each map's directrix is read once, and the bars are the same as the shaft drawn bar by bar."""
    from rebar_data.geometry import ifc_read
    from rebar_data.geometry.config import IfcMesh

    shape = {"half_m": 1.0, "storey_m": 1.2, "spacing_m": 0.3}
    mapped = write_shaft(tmp_path / "mapped.ifc", **shape)
    plain = write_shaft(tmp_path / "plain.ifc", mapped=False, **shape)
    assert len(ifcopenshell.open(str(mapped)).by_type("IfcMappedItem")) == 52
    calls: list[int] = []
    real = ifc_read.directrix_pieces

    def counted(curve, angle_rad=1.0):
        calls.append(curve.id())
        return real(curve, angle_rad)

    monkeypatch.setattr(ifc_read, "directrix_pieces", counted)
    mesh = IfcMesh(kind="ifc", ifc_path="x.ifc")
    got = ifc_read.read_ifc(mesh, mapped)
    assert len(calls) == len(set(calls)) == 6  # one directrix a map
    want = ifc_read.read_ifc(mesh, plain)
    assert len(got.bars) == len(want.bars) == 52

    def placed(bars):  # a placement's bars come together: compare in one order
        return sorted(bars, key=lambda b: tuple(np.round(b.curves[0].point(0.0), 6)))

    for a, b in zip(placed(got.bars), placed(want.bars), strict=True):
        assert [c.kind for c in a.curves] == [c.kind for c in b.curves] and a.diameter_m == b.diameter_m
        for ca, cb in zip(a.curves, b.curves, strict=True):
            np.testing.assert_allclose(ca.point(0.0), cb.point(0.0), atol=1e-9)
            np.testing.assert_allclose(ca.point(ca.length), cb.point(cb.length), atol=1e-9)


# ---------------------------------------------------------------------------------------------- bad input


def _write(path: Path, text: str | bytes) -> Path:
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


def _only_a_wall(tmp_path: Path) -> Path:
    m = Model("IFC4")
    m.element(None, ifc_class="IfcWall")
    return m.write(tmp_path / "walls.ifc")


def _no_diameter(tmp_path: Path) -> Path:
    m = Model("IFC4")
    m.bar(m.polyline([(0, 0, 0), (1, 0, 0)]), 0.0)  # no radius, and NominalDiameter 0
    return m.write(tmp_path / "flat.ifc")


def _two_bars(tmp_path: Path) -> Path:
    m = Model("IFC4")
    m.bar(m.polyline([(0, 0, 0), (1, 0, 0)]), 0.006, storey="ground")
    m.bar(m.polyline([(0.5, -0.5, 0.012), (0.5, 0.5, 0.012)]), 0.006, storey="ground")
    m.storey("roof")
    return m.write(tmp_path / "two.ifc")


def _broken_data(tmp_path: Path) -> Path:
    text = _two_bars(tmp_path).read_text()
    return _write(tmp_path / "broken.ifc", text.replace("IFCPOLYLINE((", "IFCPOLYLINE(((", 1))


def _slab_43(tmp_path: Path) -> Path:
    m = Model("IFC4")
    for k in range(43):
        m.bar(m.polyline([(0, 0.1 * k, 0), (5, 0.1 * k, 0)]), 0.006)
    return m.write(tmp_path / "slab.ifc")


def _cut_short(tmp_path: Path) -> Path:
    """An interrupted download: the first half of the file (IfcOpenShell reads 20 of its 43 bars)."""
    text = _slab_43(tmp_path).read_text()
    return _write(tmp_path / "half.ifc", text[: len(text) // 2])


def _line_skipped(tmp_path: Path) -> Path:
    """A whole file with one entity line cut off in the middle (IfcOpenShell skips it and goes on)."""
    lines = _slab_43(tmp_path).read_text().splitlines(keepends=True)
    k = next(i for i, line in enumerate(lines) if "IFCREINFORCINGBAR(" in line and i > len(lines) // 2)
    return _write(
        tmp_path / "skipped.ifc", "".join(lines[:k]) + lines[k][:30] + "\n" + "".join(lines[k + 1 :])
    )


def _only_a_brep(tmp_path: Path) -> Path:
    m = Model("IFC4")
    _faceted_bar(m)
    return m.write(tmp_path / "brep.ifc")


BAD_INPUT = {
    "missing file": (lambda t: t / "nowhere.ifc", {}, ["no such file"]),
    "a folder": (lambda t: (t / "folder.ifc").mkdir() or t / "folder.ifc", {}, ["is a folder"]),
    "not IFC (text)": (lambda t: _write(t / "notes.ifc", "name: a yaml file\n"), {}, ["not an IFC file"]),
    "not IFC (binary)": (lambda t: _write(t / "blob.ifc", bytes(range(256)) * 8), {}, ["not an IFC file"]),
    "unsupported schema": (
        lambda t: _write(
            t / "old.ifc",
            "ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION((''),'2;1');\nFILE_NAME('','',(''),(''),'','','');\n"
            "FILE_SCHEMA(('IFC2X2_FINAL'));\nENDSEC;\nDATA;\nENDSEC;\nEND-ISO-10303-21;\n",
        ),
        {},
        ["schema IFC2X2_FINAL is not read", "IFC2X3, IFC4 or IFC4X3"],
    ),
    "broken data": (_broken_data, {}, ["cannot be parsed as IFC"]),
    "cut short": (_cut_short, {}, ["is not whole", "END-ISO-10303-21;"]),
    "a line the parser skips": (
        _line_skipped,
        {},
        ["cannot be parsed as IFC whole", "of its", "entity instances"],
    ),
    "nothing readable, skipping": (
        _only_a_brep,
        {"skip_unreadable": True},
        ["none of its 1 selected elements gave a bar", "no IfcSweptDiskSolid (IfcFacetedBrep): #"],
    ),
    "no reinforcing bars": (_only_a_wall, {}, ["has no IfcReinforcingBar or IfcReinforcingMesh elements"]),
    "unknown storey": (_two_bars, {"storeys": ["level 9"]}, ["'level 9' is not a storey", "'ground'"]),
    "storey without bars": (_two_bars, {"storeys": ["roof"]}, ["mesh.storeys", "no IfcReinforcingBar"]),
    "unknown GlobalId": (_two_bars, {"global_ids": ["0" * 22]}, ["mesh.global_ids: 1 of 1", "0" * 22]),
    "box with no bars": (_two_bars, {"bbox_m": [[5, 5, 5], [6, 6, 6]]}, ["mesh.bbox_m", "no bar"]),
    "class not in the schema": (
        _two_bars,
        {"ifc_classes": ["IfcRebarCage"]},
        ["IfcRebarCage is not a class"],
    ),
    "no diameter": (_no_diameter, {}, ["a non-positive diameter"]),
    "jitter on read bars": (_two_bars, {"realism": {"jitter_m": 0.002}}, ["realism.jitter_m = 0.002"]),
    "relative path unknown": (_two_bars, {"no_config_dir": True}, ["is relative to the pipeline file"]),
}


@pytest.mark.parametrize("case", list(BAD_INPUT))
def test_bad_input_is_one_line_exit_2_and_nothing_written(case, tmp_path, capsys):
    make, mesh, words = BAD_INPUT[case]
    ifc = make(tmp_path)
    mesh = dict(mesh)
    top = {"realism": mesh.pop("realism")} if "realism" in mesh else {}
    if mesh.pop("no_config_dir", False):  # a command that does not pass the pipeline's folder
        cfg = MeshConfig.model_validate({"mesh": {"kind": "ifc", "ifc_path": ifc.name}})
        with pytest.raises(ConfigError) as e:
            build_rebar_mesh(cfg)
        assert all(w in str(e.value) for w in words), str(e.value)
        return
    cfg = pipeline(tmp_path, {"kind": "ifc", "ifc_path": ifc.name, **mesh}, **top)
    before = sorted(p.name for p in tmp_path.iterdir())
    code, err, out = mesh_cli(tmp_path, cfg, capsys)
    assert code == 2, err
    assert err.count("\n") == 0 and err.startswith("error: "), err
    assert all(w in err for w in words), err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == before


BAD_CONFIG = {
    "GlobalId of the wrong form": ({"global_ids": ["not-a-guid"]}, ["global_ids[0] = 'not-a-guid'"]),
    "empty storeys": ({"storeys": []}, ["mesh.storeys"]),
    "class name": ({"ifc_classes": ["ReinforcingBar"]}, ["ifc_classes[0] = 'ReinforcingBar'"]),
    "box inside out": ({"bbox_m": [[1, 0, 0], [0, 1, 1]]}, ["bbox_m", "below"]),
    "unknown key": ({"width_m": 2.0}, ["unknown key 'mesh.width_m'"]),
    "angle": ({"min_crossing_angle_deg": 0}, ["mesh.min_crossing_angle_deg = 0"]),
}


@pytest.mark.parametrize("case", list(BAD_CONFIG))
def test_bad_ifc_mesh_config_names_the_field(case, tmp_path, capsys):
    extra, words = BAD_CONFIG[case]
    cfg = pipeline(tmp_path, {"kind": "ifc", "ifc_path": "model.ifc", **extra})
    code, err, out = mesh_cli(tmp_path, cfg, capsys)
    assert code == 2 and err.count("\n") == 0 and not out.exists()
    assert all(w in err for w in words), err


def test_arc_through_three_points_is_exact():
    rng = np.random.default_rng(0)
    for _ in range(50):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        e1 = np.cross(axis, rng.normal(size=3))
        e1 /= np.linalg.norm(e1)
        arc = Arc(rng.normal(size=3), float(rng.uniform(0.01, 5)), axis, e1, float(rng.uniform(0.1, 6.2)))
        got = arc_through(arc.start, arc.point(arc.length / 3), arc.end)
        np.testing.assert_allclose(got.center, arc.center, atol=1e-9)
        np.testing.assert_allclose(got.axis, arc.axis, atol=1e-9)
        assert got.radius == pytest.approx(arc.radius, abs=1e-9)
        assert got.sweep == pytest.approx(arc.sweep, abs=1e-9)
    assert isinstance(Line(np.zeros(3), np.ones(3)).length, float)
