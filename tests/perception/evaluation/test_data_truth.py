"""Scoring against the projected 3D crossing points (``--truth crossing``) as well as the labels' own pixels."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest

from rebar_data.cli import main
from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import load_split
from tests.dataset.conftest import TINY, write_config


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """A rendered dataset (the tests' tiny planar pipeline, tilted views): its tables have the 3D points."""
    from rebar_data.dataset.build import build_dataset

    tmp = tmp_path_factory.mktemp("truth")
    return build_dataset(write_config(tmp, {**TINY, "name": "truth"}), tmp / "data", workers=1)


def test_crossing_truth_is_the_3d_crossing_point_projected_by_the_frames_camera(rendered):
    samples = pq.read_table(rendered / "tables/samples.parquet").to_pandas().set_index("image_id")
    kp = pq.read_table(rendered / "tables/keypoints.parquet").to_pandas()
    moved = []
    pairs = zip(load_split(rendered, "train"), load_split(rendered, "train", truth="crossing"), strict=True)
    for sight, crossing in pairs:
        assert sight.image_id == crossing.image_id and len(sight.visible) == len(crossing.visible)
        row = samples.loc[sight.image_id]
        camera_from_world = np.linalg.inv(np.asarray(row.world_from_camera, float).reshape(4, 4))
        rvec, _ = cv2.Rodrigues(camera_from_world[:3, :3])
        K = np.array([[row.fx, 0, row.cx], [0, row.fy, row.cy], [0, 0, 1]], float)
        rows = kp[(kp.image_id == sight.image_id) & (kp.visibility == 2)]
        xyz = rows[["x_crossing", "y_crossing", "z_crossing"]].to_numpy(float)
        expected, _ = cv2.projectPoints(xyz, rvec, camera_from_world[:3, 3], K, None)
        np.testing.assert_allclose(crossing.visible, expected.reshape(-1, 2), atol=1e-6)
        np.testing.assert_array_equal(sight.visible, rows[["u", "v"]].to_numpy(float))
        moved.append(np.linalg.norm(crossing.visible - sight.visible, axis=1))
    moved = np.concatenate(moved)
    # the bars lie one on the other: the 3D point, between their centerlines, projects beside the sight point
    assert moved.max() > 0.3 and np.median(moved) < 10.0


def test_score_scores_against_the_chosen_truth(rendered, tmp_path, capsys):
    figures = {}
    for truth, point in (("sight", "sight"), ("crossing", "sight"), ("crossing", None)):
        name = f"{truth}-{point}"
        metrics = tmp_path / f"{name}.json"
        args = ["score", str(rendered), "--split", "all", "--no-depth", "--quiet", "--truth", truth]
        args += ["--out", str(tmp_path / f"{name}.parquet"), "--metrics", str(metrics)]
        assert main(args + (["--point", point] if point else [])) == 0
        figures[name] = json.loads(metrics.read_text())
        assert figures[name]["truth"] == truth and figures[name]["point"] == (point or truth)
    assert "projected 3D crossing points" in capsys.readouterr().err
    sight, against, found = figures["sight-sight"], figures["crossing-sight"], figures["crossing-None"]
    assert sight["n_gt"] == against["n_gt"] == found["n_gt"] > 0
    assert sight["mean_px"] != against["mean_px"]
    # the false-detection census is taken against the labels alone
    assert (
        "false_detections" in sight and "false_detections" not in against and "false_detections" not in found
    )
    preds = [
        pq.read_table(tmp_path / f"{n}.parquet").to_pandas()
        for n in ("sight-sight", "crossing-sight", "crossing-None")
    ]
    assert preds[0].equals(preds[1])  # the same detections, scored twice
    # against the 3D points the default is the detector's own crossing points: the same detections, each
    # moved by the crossing-point stage a few pixels (the 3D point lies a bar radius behind the sight point)
    assert preds[2]["score"].equals(preds[0]["score"])
    moved = np.hypot(preds[2]["u"] - preds[0]["u"], preds[2]["v"] - preds[0]["v"])
    assert 0.3 < np.median(moved) < 10.0 and found["mean_px"] != against["mean_px"]


def test_crossing_truth_needs_the_3d_points(rendered, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(rendered, copy)
    kp = pq.read_table(copy / "tables/keypoints.parquet").drop(["x_crossing"])
    pq.write_table(kp, copy / "tables/keypoints.parquet")
    with pytest.raises(ConfigError, match="x_crossing"):
        load_split(copy, "test", truth="crossing")
    assert load_split(copy, "test")  # the labels' own pixels need no 3D point
    with pytest.raises(ConfigError, match="accepted: one of sight, crossing"):
        load_split(copy, "test", truth="midpoint")
