"""The depth a detector is judged on: the dataset's sensor depth, its exact depth, or a sensor model's image."""

import shutil

import cv2
import numpy as np
import pytest

from rebar_data.config import ConfigError
from rebar_data.dataset import layout
from rebar_data.perception.evaluation.data import DEPTH_SOURCES, load_split, read_depth, sample_depth
from rebar_data.render.depth_sensor import depth_mm

MODELS = ("structured_light", "active_stereo", "time_of_flight")


def test_a_dataset_before_sensor_depth_is_read_with_its_exact_depth(drawn_dataset):
    s = load_split(drawn_dataset, "train")[0]
    assert s.sensor_depth_path is None and s.depth_path is not None
    np.testing.assert_array_equal(sample_depth(s, "sensor"), read_depth(s.depth_path))
    np.testing.assert_array_equal(sample_depth(s, "exact"), read_depth(s.depth_path))


def test_the_sensor_depth_is_read_where_the_dataset_has_it(drawn_dataset, tmp_path):
    ds = tmp_path / "ds"
    shutil.copytree(drawn_dataset, ds)
    s = load_split(ds, "train")[0]
    exact = read_depth(s.depth_path)
    holed = exact.copy()
    holed[:, : exact.shape[1] // 3] = 0.0  # a band the sensor did not measure
    path = ds / layout.sensor_depth_path("train", s.image_id)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), depth_mm(holed))
    s = load_split(ds, "train")[0]
    assert s.sensor_depth_path == path
    np.testing.assert_allclose(sample_depth(s, "sensor"), holed, atol=6e-4)
    np.testing.assert_array_equal(sample_depth(s, "exact"), exact)


@pytest.mark.parametrize("model", MODELS)
def test_a_sensor_model_image_is_the_same_for_the_same_frame_and_loses_measurements(drawn_dataset, model):
    s = load_split(drawn_dataset, "train")[0]
    exact = read_depth(s.depth_path)
    a, b = sample_depth(s, model), sample_depth(s, model)
    np.testing.assert_array_equal(a, b)
    assert a.shape == exact.shape and a.dtype == np.float32
    measured = a > 0
    assert 0.2 < measured.mean() < 1.0  # it measures most of the frame, not all of it
    # where it measures, it measures about the exact depth (beyond edges, which misregistration moves)
    inner = measured & (cv2.erode((exact > 0).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0)
    assert np.median(np.abs(a[inner] - exact[inner])) < 0.01


def test_an_unknown_depth_source_is_refused_naming_the_accepted_ones(drawn_dataset):
    s = load_split(drawn_dataset, "train")[0]
    with pytest.raises(ConfigError, match="accepted: one of " + ", ".join(DEPTH_SOURCES)):
        sample_depth(s, "lidar")


def test_score_refuses_an_unknown_depth_source_in_one_line(drawn_dataset, tmp_path, capsys):
    from rebar_data.cli import main

    out = tmp_path / "pred.parquet"
    assert main(["score", str(drawn_dataset), "--out", str(out), "--depth-from", "lidar", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--depth-from lidar" in err[0] and "structured_light" in err[0]
    assert not out.exists()


@pytest.mark.parametrize("model", MODELS)
def test_a_frame_with_a_sensors_holes_is_read_no_worse_than_without_depth(
    rendered_frame, rendered_depth, model
):
    """The shipped detector on a rendered frame and a sensor model's image of its depth (holes along the bars'
    edges, lost thin bars, misregistration): every crossing found without depth is found with it, at the same
    point, and no detection is added."""
    from rebar_data.perception.evaluation.data import _nominal_sensor
    from rebar_data.perception.evaluation.metrics import match
    from rebar_data.perception.inference import detector as infer
    from rebar_data.render.depth_sensor import sense_depth

    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    rgb, visible, _, camera = rendered_frame
    sensed = sense_depth(rendered_depth, _nominal_sensor(model), np.random.default_rng(5), fx=camera[0])
    assert (sensed == 0).mean() > (rendered_depth == 0).mean()  # the sensor left holes
    det = infer.Detector.load(threads=1, runtime="onnxruntime", reading="single")
    without = det.detect(rgb, camera=camera)
    with_depth = det.detect(rgb, camera=camera, depth=sensed)
    found_without = match(visible, without[:, :2], 2.0)[1]
    found_with = match(visible, with_depth[:, :2], 2.0)[1]
    assert len(found_without) >= 5 and set(found_without) <= set(found_with)
    assert len(with_depth) <= len(without)


def test_a_depth_image_of_another_size_is_named(tmp_path):
    from rebar_data.perception.evaluation.data import Sample

    depth = tmp_path / "depth" / "test" / "a.png"
    depth.parent.mkdir(parents=True)
    cv2.imwrite(str(depth), np.full((30, 40), 1000, np.uint16))
    s = Sample("a", tmp_path / "a.png", 160, 120, np.zeros((0, 2)), np.zeros(0), depth_path=depth)
    for source in ("exact", "structured_light"):
        with pytest.raises(
            ConfigError, match=rf"{depth}: a depth image of 40x30 px; accepted: .* 160x120 px"
        ):
            sample_depth(s, source)
    cv2.imwrite(str(depth), np.full((120, 160), 1000, np.uint16))
    assert sample_depth(s, "exact").shape == (120, 160)


def test_a_truncated_info_json_is_named(tmp_path):
    from rebar_data.perception.evaluation.data import read_info

    (tmp_path / "meta").mkdir()
    (tmp_path / "meta" / "info.json").write_text('{"name": "tiny", "oks_sig')
    with pytest.raises(ConfigError, match=r"meta/info.json: not valid JSON .*expected the info file"):
        read_info(tmp_path)
