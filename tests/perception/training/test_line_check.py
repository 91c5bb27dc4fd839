from __future__ import annotations

import cv2
import numpy as np
import pytest

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import load_split, read_depth, read_sample_image
from rebar_data.perception.inference import checks as lc
from rebar_data.perception.inference.checks import FEATURES, LineCheck
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.networks.files import update_onnx_meta
from rebar_data.perception.training.config import LineCheckConfig
from rebar_data.perception.training.line_check import fit_line_check, line_check_meta
from tests.perception.conftest import shipped_model_copy


def _angle_apart(a: np.ndarray, b: float) -> np.ndarray:
    """Degrees between bar directions (modulo 180)."""
    return np.abs((np.degrees(a) - b + 90.0) % 180.0 - 90.0)


def test_the_two_bar_directions_are_read_from_the_image():
    img = np.full((240, 320, 3), 90, np.uint8)
    c = np.array([160.0, 120.0])
    for deg, width in ((20.0, 12), (110.0, 8)):
        d = np.array([np.cos(np.radians(deg)), np.sin(np.radians(deg))]) * 300
        cv2.line(img, tuple((c - d).astype(int)), tuple((c + d).astype(int)), (200, 170, 140), width)
    got = lc.bar_directions(img, np.array([c, c + [0.5, 0.5]]))
    for row in got:
        assert sorted([_angle_apart(row, 20.0).min(), _angle_apart(row, 110.0).min()])[1] <= 3.0, np.degrees(
            row
        )
    assert lc.bar_directions(img, np.zeros((0, 2))).shape == (0, 2)
    # a point off the image (the second stage may place one there) reads the nearest window on it
    off = lc.bar_directions(img, np.array([[-30.0, -40.0], [400.0, 300.0], [0.0, 0.0], [319.0, 239.0]]))
    np.testing.assert_array_equal(off[:2], off[2:])


def test_a_curved_bar_is_followed_and_the_bar_beside_it_is_not():
    t = np.arange(-5, 6) * 40.0 / 700.0  # points 40 px apart on an arc of radius 700 px
    arc = np.c_[400 + 700 * np.sin(t), 700 - 700 * np.cos(t) + 100]
    beside = arc[:, :] + [0.0, 15.0]  # a second row 15 px off, where a lower bar would show
    uv = np.r_[arc, beside]
    start = 5  # the arc's middle point
    members = lc.bar_members(uv, np.array([[0.0, np.pi / 2]]), np.array([start]))
    assert members.shape == (1, 2, 2 * lc.STEPS)
    along = members[0, 0][members[0, 0] >= 0]
    assert sorted(along.tolist()) == [i for i in range(len(arc)) if i != start]
    # across the arc the nearest candidate ahead is the row beside it, 15 px away
    assert members[0, 1][members[0, 1] >= 0].tolist() == [start + len(arc)]


def test_the_features_summarise_the_scores_along_each_bar():
    score = np.array([0.7, 0.9, 0.6, 0.3, 0.1, 0.85])
    members = np.full((1, 2, 2 * lc.STEPS), -1)
    members[0, 0, :1] = [4]  # the worse bar: one candidate scored 0.1
    members[0, 1, :4] = [1, 2, 3, 5]  # the better one
    x = lc.features(score, members, np.array([0]))[0]
    named = dict(zip(FEATURES, x, strict=True))
    v = np.array([0.9, 0.6, 0.3, 0.85])
    assert named["own_logit"] == pytest.approx(np.log(0.7 / 0.3))
    assert named["better_bar_count"] == 4
    assert named["better_bar_mean"] == pytest.approx(v.mean())
    assert named["better_bar_upper_quartile"] == pytest.approx(np.quantile(v, 0.75))
    assert named["better_bar_best"] == pytest.approx(0.9)
    assert named["better_bar_share_high"] == pytest.approx(0.5)
    assert named["better_bar_share_above_own"] == pytest.approx(0.5)
    assert named["better_bar_best_two"] == pytest.approx(0.875)
    assert named["other_bar_count"] == 1 and named["other_bar_best_two"] == pytest.approx(0.1)
    none = np.full((1, 2, 2 * lc.STEPS), -1)
    assert not lc.features(score, none, np.array([0]))[0, 1:].any()  # no bars followed: zeros


def _random_check(seed: int) -> LineCheck:
    """A check that weighs the candidate's own score most, as the fitted ones do."""
    rng = np.random.default_rng(seed)
    w = rng.normal(0, 0.5, len(FEATURES))
    w[0] = 3.0
    w[[FEATURES.index("better_bar_count"), FEATURES.index("other_bar_count")]] *= 0.05
    return LineCheck(w, -1.0)


def test_only_candidates_the_check_could_not_lift_to_the_threshold_are_spared():
    rng = np.random.default_rng(4)
    img = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    uv = rng.uniform([0, 0], [320, 240], (60, 2))
    evidence = rng.uniform(0.05, 1.0, 60)
    checked = np.flatnonzero(evidence >= 0.2)
    for seed in range(3):
        check = _random_check(seed)
        every = check.scores(img, uv, evidence, checked, threshold=1e-6)
        at = check.scores(img, uv, evidence, checked, threshold=0.5)
        assert (at == 0).sum() > 0  # some were spared
        np.testing.assert_array_equal(at[every >= 0.5], every[every >= 0.5])
        assert (every[at == 0] < 0.5).all()


def test_line_check_settings_keep_the_checked_candidates_among_the_evidence():
    assert LineCheckConfig(floor=0.1, checked_from=0.1).checked_from == 0.1
    with pytest.raises(ValueError, match="0 < floor <= checked_from < 1"):
        LineCheckConfig(floor=0.4, checked_from=0.3)


def test_a_check_fitted_on_other_features_is_refused():
    entry = line_check_meta(_random_check(0))
    assert LineCheck.from_meta(entry, "m.onnx").weights.tolist() == entry["weights"]
    with pytest.raises(ConfigError, match="line check reads"):
        LineCheck.from_meta({**entry, "features": entry["features"][:-1]}, "m.onnx")
    with pytest.raises(ConfigError, match="fitted reading the bars with"):
        LineCheck.from_meta({**entry, "reading": {**entry["reading"], "steps": 10}}, "m.onnx")


@pytest.fixture(scope="module")
def checked_model(drawn_dataset, tmp_path_factory):
    """A copy of the shipped model with a line check fitted on the drawn frames written into it (a model
    trained in a test finds too few crossings to fit one)."""
    model = shipped_model_copy(tmp_path_factory.mktemp("checked"))
    val = load_split(drawn_dataset, "val")
    detector = Detector.load(model, threads=2, runtime="onnxruntime")
    detector.line_check = None
    entry, _ = fit_line_check(
        detector, val + load_split(drawn_dataset, "train"), val, LineCheckConfig(), data=["drawn"]
    )
    update_onnx_meta(model, {"line_check": entry})
    return model, entry


def test_the_fitted_check_in_the_model_file_loads_with_it(checked_model):
    from rebar_data.perception.training.card import stage_rows

    model, entry = checked_model
    assert entry["fitted_on"] == ["drawn"] and entry["candidates"] > entry["crossings"] > 0
    det = Detector.load(model, threads=1)
    assert det.line_check is not None
    np.testing.assert_allclose(det.line_check.weights, entry["weights"])
    assert f"fitted on {entry['candidates']} candidates of `drawn`" in stage_rows(model, det, {})[-1][-1]


def test_with_a_line_check_the_detector_returns_the_same_at_any_threshold(checked_model, drawn_dataset):
    """The check spares the second stage's later passes and its own reading for candidates it cannot lift
    to the threshold; what it returns at the operating point is what it returns at a low threshold, cut
    there. With a depth image the same detections come, at the same points, with scores no higher."""
    model, _ = checked_model
    det = Detector.load(model, threads=1)
    samples = load_split(drawn_dataset, "val") + load_split(drawn_dataset, "test")

    changed = 0
    for s in samples:
        rgb = read_sample_image(s)
        low = det.detect(rgb, camera=s.camera, threshold=0.05)
        at = det.detect(rgb, camera=s.camera, threshold=0.3)
        np.testing.assert_array_equal(at, low[low[:, 2] >= 0.3])
        with_depth = det.detect(rgb, camera=s.camera, depth=read_depth(s.depth_path), threshold=0.05)
        same = (with_depth[:, None, :2] == low[None, :, :2]).all(axis=2)
        assert same.any(axis=1).all()
        assert (with_depth[:, 2] <= low[same.argmax(axis=1), 2] + 1e-9).all()
        check, det.line_check = det.line_check, None
        try:
            plain = det.detect(rgb, camera=s.camera, threshold=0.05)
        finally:
            det.line_check = check
        changed += len(plain) != len(low) or not np.allclose(plain[:, 2], low[:, 2])
    assert changed  # the check changed some scores
