"""`rebar adapt`: a model file's first stage trained a few more epochs on another camera's frames."""

from __future__ import annotations

import numpy as np
import pytest

from rebar_data.cli import main
from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import load_split, read_sample_image
from rebar_data.perception.evaluation.evaluate import load_splits
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.networks.files import onnx_meta
from rebar_data.perception.training.adapt import adapt_model
from rebar_data.perception.training.config import resolve_config
from tests.perception.conftest import TINY_TRAIN
from tests.perception.synthetic import SyntheticSpec, write_synthetic_dataset


@pytest.fixture(scope="module")
def other_frames(tmp_path_factory):
    """Frames of another camera: a drawn dataset of its own name, seed and size."""
    spec = SyntheticSpec(width=176, height=128, focal_px=150.0, trajectories=2, frames=2)
    return write_synthetic_dataset(tmp_path_factory.mktemp("other"), spec, seed=23, name="other-camera")


def test_the_adapted_model_keeps_the_later_stages_and_detects(
    trained_run, drawn_dataset, other_frames, tmp_path
):
    model = trained_run.out_dir / "best.onnx"
    cfg = resolve_config(TINY_TRAIN, {})
    samples, frames = load_split(drawn_dataset, "train"), load_splits(other_frames)

    def adapt():
        return adapt_model(model, samples, frames, tmp_path / "a", cfg, data=["other"])

    out = adapt()
    assert out == tmp_path / "a" / "rebar_keypoint.onnx"
    # the later stages the model had came along, byte for byte
    for later in sorted(trained_run.out_dir.glob("best.*.onnx")):
        copied = out.with_name(later.name.replace("best.", "rebar_keypoint.", 1))
        assert copied.read_bytes() == later.read_bytes()
    meta = onnx_meta(out)
    assert meta["adapted_from"] == str(model) and meta["adapt"]["epochs_run"] == cfg.adapt.epochs
    rgb = read_sample_image(frames[0])
    before = Detector.load(model, threads=1).raw(rgb)
    after = Detector.load(out, threads=1)
    assert after.refiner is not None and not np.allclose(after.raw(rgb), before, atol=1e-3)  # it trained
    assert after.detect(rgb, threshold=0.05).shape[1] == 3
    # run again, it resumes: the same file, no epoch trained again
    again = adapt()
    np.testing.assert_allclose(Detector.load(again, threads=1).raw(rgb), after.raw(rgb), atol=1e-6)


def test_bad_inputs_are_refused_before_any_training(trained_run, drawn_dataset, other_frames, tmp_path):
    model = trained_run.out_dir / "best.onnx"
    cfg = resolve_config(TINY_TRAIN, {})
    samples, frames = load_split(drawn_dataset, "train"), load_splits(other_frames)
    with pytest.raises(ConfigError, match="no frames to adapt to"):
        adapt_model(model, samples, [], tmp_path / "b", cfg, data=[])
    with pytest.raises(ConfigError, match="is not an ONNX file"):
        adapt_model(trained_run.out_dir / "best.pt", samples, frames, tmp_path / "b", cfg, data=[])
    none = resolve_config({**TINY_TRAIN, "adapt": {"epochs": 0}}, {})
    with pytest.raises(ConfigError, match="adapt.epochs = 0"):
        adapt_model(model, samples, frames, tmp_path / "b", none, data=[])
    assert not (tmp_path / "b").exists()  # nothing half-written


def test_rebar_adapt_refuses_the_frames_of_the_dataset_itself(trained_run, drawn_dataset, tmp_path, capsys):
    argv = ["adapt", str(drawn_dataset), "--frames", str(drawn_dataset)]
    argv += ["--model", str(trained_run.out_dir / "best.onnx"), "--out", str(tmp_path / "c"), "--quiet"]
    assert main(argv) == 2
    assert "whose val and test scenes a supplement would train on" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()


def test_adapt_draws_the_other_cameras_crops_at_the_models_focal_length(
    trained_run, drawn_dataset, other_frames, tmp_path, monkeypatch
):
    """The adapt epochs crop another camera's frames at the focal length the model trained at, as `detect`
    will read them (``rebar_data.perception.inference.image``)."""
    from rebar_data.perception.training import adapt as adapt_train

    model = trained_run.out_dir / "best.onnx"
    asked: dict = {}

    class Stop(Exception):
        pass

    def stream(*args, **kwargs):
        asked.update(kwargs)
        raise Stop

    monkeypatch.setattr(adapt_train, "batch_stream", stream)
    cfg = resolve_config(TINY_TRAIN, {})
    with pytest.raises(Stop):
        adapt_model(
            model,
            load_split(drawn_dataset, "train"),
            load_splits(other_frames),
            tmp_path / "a",
            cfg,
            data=["o"],
        )
    assert asked["focal_px"] == onnx_meta(model)["focal_px"] == 157.5
