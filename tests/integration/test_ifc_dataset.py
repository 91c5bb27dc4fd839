"""A dataset whose mesh is read from IFC (the sample wall: two mats, stirrups, U-bars, off the origin and
vertical) builds, validates and passes its audit; it carries its own copy of the model, so the audit and the
bundle need nothing outside it."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest

pytest.importorskip("ifcopenshell")

from rebar_data.cli import main  # noqa: E402
from rebar_data.dataset import layout  # noqa: E402
from rebar_data.dataset.build import build_dataset  # noqa: E402
from rebar_data.geometry.ifc_samples import world_from_wall, write_wall  # noqa: E402
from tests.dataset.conftest import write_config  # noqa: E402

WALL = {
    "name": "tiny-wall",
    "version": "0.0.1",
    "seed": 3,
    "mesh": {"kind": "ifc", "ifc_path": "model/wall.ifc", "crossings": "top_mat"},
    "realism": {"tie_wire_fraction": 0.5},
    "camera": {
        "intrinsics": {"width": 160, "height": 120, "fx": 150.0, "fy": 150.0, "cx": 80.0, "cy": 60.0},
        "trajectories": [
            {"kind": "orbit_arc", "count": 2, "frames": 2, "edge_margin_m": 0.2},
            {
                "kind": "random_look_at",
                "count": 1,
                "frames": 2,
                "edge_margin_m": 0.2,
                "tilt_deg": [30.0, 50.0],
            },
        ],
    },
    "dataset": {"split": {"rule": "scene", "train": 0.34, "val": 0.33, "test": 0.33}},
}


@pytest.fixture(scope="module")
def wall_dataset(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cfg")
    (folder / "model").mkdir()
    write_wall(folder / "model/wall.ifc")
    cfg = write_config(folder, WALL, "wall.yaml")
    return build_dataset(cfg, tmp_path_factory.mktemp("ds"), workers=1), folder


def test_a_dataset_of_an_ifc_wall_validates_and_audits_clean(wall_dataset, tmp_path, capsys):
    ds, source = wall_dataset
    copy = tmp_path / "wall"
    shutil.copytree(ds, copy)
    shutil.rmtree(source / "model")  # the audit reads the dataset's own copy of the model
    assert (copy / layout.MESH_IFC).read_bytes()[:13] == b"ISO-10303-21;"
    manifest = pq.read_table(copy / layout.MANIFEST).to_pandas()
    assert layout.MESH_IFC in set(manifest.path)
    assert main(["dataset", "validate", str(copy)]) == 0
    assert main(["dataset", "audit", str(copy)]) == 0
    capsys.readouterr()
    report = json.loads((copy / "audit/report.json").read_text())
    checks = {c["name"]: c for c in report["checks"]}
    assert report["passed"] and checks["reprojection_px"]["value"] < 1e-3
    assert (
        checks["geometry_m"]["passed"]
        and "85 crossings in the rebuilt mesh" in checks["geometry_m"]["detail"]
    )
    assert checks["visible_on_own_bar"]["passed"] and (copy / "audit/contact_sheet.png").stat().st_size > 0
    # every image looks at the wall's front (its +x side) and sees some of the front mat's crossings
    S = pq.read_table(copy / layout.SAMPLES).to_pandas()
    K = pq.read_table(copy / layout.KEYPOINTS).to_pandas()
    front = world_from_wall()[:3, 1]
    for row in S.itertuples():
        T = np.asarray(row.world_from_camera).reshape(4, 4)
        assert (T[:3, 3] - world_from_wall()[:3, 3]) @ front > 0.3 and T[:3, 2] @ front < -0.5
    assert (K.groupby("image_id").visibility.apply(lambda v: (v == 2).sum()) > 0).all()
    crossings = K[["x_crossing", "y_crossing", "z_crossing"]].to_numpy()
    assert np.all((crossings - world_from_wall()[:3, 3]) @ front > 0.05)  # the front mat's, none behind


def test_an_ifc_dataset_without_its_model_copy_fails_validation(wall_dataset, tmp_path, capsys):
    ds, _ = wall_dataset
    copy = tmp_path / "wall"
    shutil.copytree(ds, copy)
    (copy / layout.MESH_IFC).write_bytes(b"ISO-10303-21;\n")
    assert main(["dataset", "validate", str(copy)]) == 1
    assert "meta/mesh.ifc" in capsys.readouterr().out


def test_the_bundle_of_an_ifc_dataset_ships_the_model(wall_dataset, tmp_path, capsys):
    ds, _ = wall_dataset
    bundle = tmp_path / "bundle"
    assert main(["dataset", "publish", str(ds), "--out", str(bundle)]) == 0
    capsys.readouterr()
    assert (bundle / layout.MESH_IFC).read_bytes() == (ds / layout.MESH_IFC).read_bytes()
    croissant = json.loads((bundle / "croissant.json").read_text())
    assert layout.MESH_IFC in json.dumps(croissant)
    assert layout.MESH_IFC in (bundle / "SHA256SUMS").read_text()
    assert "read from an IFC building model" in (bundle / "README.md").read_text()


def test_every_crossing_of_the_wall_audits_clean_also_on_stirrup_bends(tmp_path, capsys):
    """``crossings: all``: both mats, the stirrups' bends (20 mm radius, closed loops) and legs, the U-bars;
    sight points on bent and closed bars stay on their centerlines, and occluded keypoints agree with the
    instance maps."""
    (tmp_path / "model").mkdir()
    write_wall(tmp_path / "model/wall.ifc")
    data = {**WALL, "name": "tiny-wall-all", "mesh": {**WALL["mesh"], "crossings": "all"}}
    data["camera"] = {
        **WALL["camera"],
        "trajectories": [{"kind": "random_look_at", "count": 3, "frames": 2, "tilt_deg": [0.0, 60.0]}],
    }
    ds = build_dataset(write_config(tmp_path, data, "all.yaml"), tmp_path / "ds", workers=1)
    assert main(["dataset", "validate", str(ds)]) == 0
    assert main(["dataset", "audit", str(ds)]) == 0
    capsys.readouterr()
    checks = {c["name"]: c for c in json.loads((ds / "audit/report.json").read_text())["checks"]}
    assert "194 crossings in the rebuilt mesh" in checks["geometry_m"]["detail"]
    assert checks["geometry_m"]["value"] < 1e-9
