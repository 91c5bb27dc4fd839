from __future__ import annotations

import pytest

from rebar_data.config import ConfigError
from rebar_data.perception.card import CARD_NAME, ship
from rebar_data.perception.infer import Detector


def test_ship_copies_the_best_model_and_writes_its_card(trained_run, tmp_path):
    model = ship(trained_run.out_dir, models_dir=tmp_path)
    assert model.name == "rebar_keypoint.onnx" and model.stat().st_size < 5 * 2**20
    assert (tmp_path / "rebar_keypoint.refine.onnx").is_file()  # the second stage travels with it
    card = (tmp_path / CARD_NAME).read_text()
    assert "OKS sigma 0.04" in card and "| drawn test |" in card and "make train" in card
    assert "| drawn test, first stage alone |" in card and "rebar_keypoint.refine.onnx" in card
    # where the test split's errors lie: the frames' inside (the drawn set has no lower-mat column)
    assert "| drawn test, crossings >= 8 px inside the frame |" in card and "lower mat |" not in card
    # the second stage's verification is described where the model and its training are
    assert "sigmoid(first-stage logit + 0.5 log p)" in card and "farther than 6 px from every" in card
    # latency is timed on rendered frames like the training data's, not on the drawn worst case
    assert "over 8 rendered paper-tunnel frames" in card and "candidates" in card
    det = Detector.load(model)
    assert det.meta["dataset"]["name"] == "drawn" and det.refiner is not None


def test_ship_refuses_an_unfinished_run(tmp_path):
    with pytest.raises(ConfigError, match="finished"):
        ship(tmp_path, models_dir=tmp_path / "models")
