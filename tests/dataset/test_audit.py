from __future__ import annotations

import copy as copy_module
import json
import shutil

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from rebar_data.cli import main
from rebar_data.dataset.audit import audit_dataset


@pytest.fixture
def copy(tiny_dataset, tmp_path):
    dst = tmp_path / "ds"
    shutil.copytree(tiny_dataset, dst)
    return dst


def _failed(ds) -> set[str]:
    checks, _ = audit_dataset(ds)
    return {c.name for c in checks if not c.passed}


def test_audit_command_writes_a_report_and_exits_zero(copy, capsys):
    assert main(["dataset", "audit", str(copy)]) == 0
    report = json.loads((copy / "audit/report.json").read_text())
    assert report["passed"] is True
    assert {c["name"] for c in report["checks"]} >= {
        "reprojection_px",
        "formats_agree_px",
        "visible_on_own_bar",
        "occluded_off_own_bar",
        "visible_at_own_depth",
        "duplicate_images",
        "scene_id_in_two_splits",
    }


def test_a_label_off_by_a_hundredth_of_a_pixel_fails_reprojection(copy):
    p = copy / "tables/keypoints.parquet"
    t = pq.read_table(p).to_pandas()
    t.loc[t.index[t.visibility == 2][0], "u"] += 0.01
    pq.write_table(pa.Table.from_pandas(t, schema=pq.read_schema(p), preserve_index=False), p)
    assert {"reprojection_px", "formats_agree_px"} <= _failed(copy)


def test_visible_keypoints_called_occluded_fail_the_rendered_passes_check(copy):
    """The rendered instance and depth passes catch a wrong visibility: a handful of visible keypoints
    (a pixel showing their own bar at the crossing) marked occluded fail occluded_off_own_bar; a single one
    passes it, as one sub-pixel occluder the rendered pass misses would."""
    p = copy / "tables/keypoints.parquet"
    t = pq.read_table(p).to_pandas()
    visible = t.index[t.visibility == 2]
    assert len(visible) >= 4
    one = t.copy()
    one.loc[visible[:1], "visibility"] = 1
    pq.write_table(pa.Table.from_pandas(one, schema=pq.read_schema(p), preserve_index=False), p)
    assert "occluded_off_own_bar" not in _failed(copy)
    t.loc[visible[:4], "visibility"] = 1
    pq.write_table(pa.Table.from_pandas(t, schema=pq.read_schema(p), preserve_index=False), p)
    assert "occluded_off_own_bar" in _failed(copy)


def test_a_visible_label_whose_pixel_shows_the_ground_fails_the_depth_check(copy):
    """A label between two bars' images, where the ground shows through, has bars in the 3x3 pixels around
    it but not under it: visible_at_own_depth sees that."""
    import cv2
    import numpy as np

    from rebar_data.dataset.layout import INSTANCE_OFFSET

    keypoints = pq.read_table(copy / "tables/keypoints.parquet").to_pandas()
    samples = pq.read_table(copy / "tables/samples.parquet").to_pandas().set_index("image_id")
    visible = keypoints[keypoints.visibility == 2]
    assert len(visible) >= 10
    for image_id, group in visible.groupby("image_id"):
        path = copy / samples.loc[image_id, "instance_file"]
        inst = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        inst[np.floor(group.v).astype(int), np.floor(group.u).astype(int)] = INSTANCE_OFFSET - 2  # ground
        cv2.imwrite(str(path), inst)
    assert "visible_at_own_depth" in _failed(copy)


def test_a_yolo_file_of_another_image_fails_format_agreement(copy):
    labels = sorted((copy / "labels").rglob("*.txt"), key=lambda p: p.stat().st_size)
    labels[0].write_text(labels[-1].read_text())
    assert _failed(copy) == {"formats_agree_px"}


def test_duplicate_images_and_split_leakage_are_caught(copy):
    imgs = sorted((copy / "images/train").glob("*.png"))
    shutil.copy(imgs[0], imgs[1])
    p = copy / "tables/samples.parquet"
    t = pq.read_table(p).to_pandas()
    t.loc[t.index[t.split == "val"][0], "split"] = "train"
    pq.write_table(pa.Table.from_pandas(t, schema=pq.read_schema(p), preserve_index=False), p)
    failed = _failed(copy)
    assert "duplicate_images" in failed and "scene_id_in_two_splits" in failed


def _by_name(checks) -> dict:
    return {c.name: c for c in checks}


PASS_CHECKS = ("visible_on_own_bar", "occluded_off_own_bar", "visible_at_own_depth")


def test_rendered_pass_checks_with_no_maps_to_read_fail_saying_nothing_was_checked(copy):
    """A dataset built to store its depth and instance maps whose rows name none has not had its
    visibility checked: the checks fail and say so, where they used to pass with 0 keypoints checked."""
    p = copy / "tables/samples.parquet"
    t = pq.read_table(p).to_pandas()
    t["depth_file"] = None
    t["instance_file"] = None
    pq.write_table(pa.Table.from_pandas(t, schema=pq.read_schema(p), preserve_index=False), p)
    checks = _by_name(audit_dataset(copy)[0])
    for name in PASS_CHECKS:
        assert not checks[name].passed, checks[name]
        assert "nothing checked" in checks[name].detail and "12 of 12 images" in checks[name].detail


@pytest.fixture(scope="module")
def mapless_dataset(tmp_path_factory):
    """TINY built with dataset.store_depth and store_instances off."""
    from rebar_data.dataset.build import build_dataset
    from tests.dataset.conftest import TINY, write_config

    data = copy_module.deepcopy(TINY)
    data["dataset"] = {"store_depth": False, "store_instances": False}
    root = tmp_path_factory.mktemp("mapless")
    return build_dataset(write_config(root / "cfg", data), root, workers=1)


def test_a_dataset_built_without_maps_validates_and_its_pass_checks_do_not_apply(mapless_dataset, capsys):
    from rebar_data.dataset.validate import validate_dataset

    assert validate_dataset(mapless_dataset) == []
    checks, _ = audit_dataset(mapless_dataset)
    by = _by_name(checks)
    for name in PASS_CHECKS:
        assert by[name].passed and not by[name].applicable, by[name]
        assert by[name].bar.startswith("not applicable") and "store_" in by[name].bar
    assert all(c.passed for c in checks)
    assert all(c.applicable for c in checks if c.name not in PASS_CHECKS)
    report = (mapless_dataset / "audit/report.md").read_text()
    assert "| visible_on_own_bar | n/a |" in report
    capsys.readouterr()
    assert main(["dataset", "audit", str(mapless_dataset)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert any(line.startswith("n/a   visible_on_own_bar") for line in printed), printed
    assert any(line.startswith("pass  reprojection_px") for line in printed), printed


def test_leakage_under_the_trajectory_rule_names_trajectories_and_does_not_apply_to_scenes(copy):
    info = copy / "meta/info.json"
    data = json.loads(info.read_text())
    data["split"]["rule"] = "trajectory"
    info.write_text(json.dumps(data))
    by = _by_name(audit_dataset(copy)[0])
    assert not by["scene_id_in_two_splits"].applicable and by["scene_id_in_two_splits"].passed
    assert by["trajectory_id_in_two_splits"].applicable
    assert by["trajectory_id_in_two_splits"].detail.startswith("trajectories present")


def test_coverage_shows_the_parameters_that_vary_and_the_report_lists_the_constant_ones(copy):
    import cv2

    _, stats = audit_dataset(copy)
    report = json.loads((copy / "audit/report.json").read_text())
    constant = report["constant_parameters"]
    samples = pq.read_table(copy / "tables/samples.parquet").to_pandas()
    assert constant and all(samples[name].nunique() == 1 for name in constant)
    assert "light_exposure_lux" in constant  # one value for every scene of TINY
    assert stats["varying_parameters"] + len(constant) == stats["randomized_columns"]
    assert "## Constant parameters" in (copy / "audit/report.md").read_text()
    h, w = cv2.imread(str(copy / "audit/coverage.png")).shape[:2]
    assert w <= 2000 and h <= 2400, (w, h)
