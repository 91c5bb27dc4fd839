"""Training from a model you have (``rebar train --init``): the stages read back from its files, the stages
named trained on from their weights, the others kept as they are."""

from __future__ import annotations

import json

import numpy as np
import onnxruntime as ort
import pytest
import torch

from rebar_data.config import ConfigError
from rebar_data.digest import sha256_file
from rebar_data.perception.training.init import parse_stages, read_model
from rebar_data.perception.training.train import train
from tests.perception.conftest import TINY_TRAIN

QUICK_INIT = {"init": {"epochs": 1, "stage_epochs": 1}}


def _outputs(net, name, rng):
    """The stage ``name``'s outputs for random inputs, from the network and as ONNX Runtime feeds them."""
    p = net.patch_px
    if name == "depth_check":
        x = rng.normal(size=(5, 2, p, p)).astype(np.float32)
        return {"depth": x}, net(torch.from_numpy(x))
    if name == "refine":
        x = rng.integers(0, 256, (5, p, p, net.channels), dtype=np.uint8)
        return {"patches": x}, net(torch.from_numpy(x).permute(0, 3, 1, 2).float())
    x = rng.integers(0, 256, (5, p, p, 3), dtype=np.uint8)
    rays = rng.normal(size=(5, 2)).astype(np.float32)
    return {"patches": x, "rays": rays}, net(
        torch.from_numpy(x).permute(0, 3, 1, 2).float(), torch.from_numpy(rays)
    )


def test_the_shipped_model_reads_back_into_every_stage_network_exactly():
    model = read_model(None)
    assert set(model.stages) == {"refine", "depth_check", "crossing_point"} and "int8" in model.files
    rng = np.random.default_rng(0)
    for name, net in model.stages.items():
        feed, torch_out = _outputs(net, name, rng)
        sess = ort.InferenceSession(str(model.files[name]), providers=["CPUExecutionProvider"])
        np.testing.assert_allclose(sess.run(None, feed)[0], torch_out.detach().numpy(), atol=1e-4)
    assert sum(p.numel() for p in model.first.parameters()) > 100_000


def test_stages_not_named_are_kept_byte_for_byte(trained_run, drawn_dataset, tmp_path):
    base = trained_run.out_dir
    out = tmp_path / "depth-only"
    train(
        drawn_dataset, out, config=QUICK_INIT, init=base / "best.onnx", stages="depth_check", progress=False
    )
    for name in ("refine", "refine.int8", "crossing"):
        a, b = base / f"best.{name}.onnx", out / f"best.{name}.onnx"
        assert a.exists() == b.exists() and (not a.exists() or sha256_file(a) == sha256_file(b)), name
    assert sha256_file(base / "best.depth.onnx") != sha256_file(out / "best.depth.onnx")
    from rebar_data.perception.networks.files import onnx_meta

    was, now = onnx_meta(base / "best.onnx"), onnx_meta(out / "best.onnx")
    from rebar_data.perception.inference.detector import Detector

    # the operating point the run time reads from each file (an older file's own key included) is the same
    assert Detector.load(out).score_bias == Detector.load(base).score_bias
    assert now.get("line_check") == was.get("line_check")
    assert now["refiner"] == was["refiner"] and now["crossing_point"] == was["crossing_point"]
    record = json.loads((out / "results.json").read_text())["dataset"]["init"]
    assert record["stages"] == ["depth_check"] and record["sha256"] == sha256_file(base / "best.onnx")


def test_a_stage_trained_from_a_model_starts_from_its_weights(trained_run, drawn_dataset, tmp_path):
    """One epoch from the trained model's weights starts where that model left off: the first stage's first
    epoch has a lower loss than the same epoch from nothing, and each later stage ends near the model's
    weights (nearer than one trained from nothing), its batch norms as the model's file left them."""
    from rebar_data.perception.training import crossing_point, depth_check, refine

    base = trained_run.out_dir
    fresh = train(drawn_dataset, tmp_path / "fresh", config={**TINY_TRAIN, "epochs": 1}, progress=False)
    tuned = train(
        drawn_dataset, tmp_path / "tuned", config=QUICK_INIT, init=base / "best.onnx", progress=False
    )
    assert tuned.history[0]["train_loss"] < fresh.history[0]["train_loss"]
    start = read_model(base / "best.onnx").stages
    for stage, module, name in (
        ("refine", refine, "refine"),
        ("depth_check", depth_check, "depth"),
        ("crossing_point", crossing_point, "crossing"),
    ):
        was = start[stage].state_dict()
        now = module.load(tmp_path / f"tuned/best.{name}.pt")[0].state_dict()
        other = module.load(tmp_path / f"fresh/best.{name}.pt")[0].state_dict()
        weights = [k for k, v in was.items() if k.endswith("weight") and v.dim() > 1]
        moved = sum(float((now[k] - was[k]).norm()) for k in weights)
        apart = sum(float((other[k] - was[k]).norm()) for k in weights)
        assert 0 < moved < apart, stage
        norms = [k for k in was if k.endswith("running_var")]
        assert norms and all(torch.equal(now[k], was[k]) for k in norms), stage
    # the run's settings are the model's (its networks' shapes), the init section's epochs laid over them
    saved = json.loads((tmp_path / "tuned/config.json").read_text())["train_config"]
    assert saved["model"] == json.loads((base / "config.json").read_text())["train_config"]["model"]


def test_init_and_stages_refuse_what_they_cannot_do(trained_run, drawn_dataset, tmp_path):
    with pytest.raises(ConfigError, match="--stages together with --init"):
        train(drawn_dataset, tmp_path / "a", config=TINY_TRAIN, stages="refine", progress=False)
    with pytest.raises(ConfigError, match="accepted: a comma-separated list of first, refine"):
        parse_stages("first,backbone")
    assert parse_stages("depth_check, first") == ("first", "depth_check")
    (tmp_path / "x.pt").write_bytes(b"")
    with pytest.raises(ConfigError, match="--init reads a model's .onnx file"):
        read_model(tmp_path / "x.pt")
    out = tmp_path / "b"
    train(drawn_dataset, out, config=QUICK_INIT, init=trained_run.out_dir / "best.onnx", progress=False)
    with pytest.raises(ConfigError, match="started from"):  # the same folder, from nothing: not a resume
        train(drawn_dataset, out, config={**TINY_TRAIN, "epochs": 1}, progress=False)


def test_the_shipped_model_trains_one_stage_and_keeps_its_operating_point(drawn_dataset, tmp_path):
    """From the shipped model (no run records, its ONNX files alone), the depth check alone: the other stages'
    files are the shipped ones, and the run time reads the same operating point and line check from both."""
    from rebar_data.perception.inference.detector import SHIPPED_MODEL, Detector

    out = tmp_path / "run"
    train(drawn_dataset, out, config=QUICK_INIT, init=SHIPPED_MODEL, stages="depth_check", progress=False)
    shipped, tuned = Detector.load(None, runtime="onnxruntime"), Detector.load(out, runtime="onnxruntime")
    assert tuned.score_bias == shipped.score_bias
    assert tuned.meta["line_check"] == shipped.meta["line_check"]
    for name in ("refine", "refine.int8", "crossing"):
        assert sha256_file(out / f"best.{name}.onnx") == sha256_file(
            SHIPPED_MODEL.with_name(f"rebar_keypoint.{name}.onnx")
        )
    assert sha256_file(out / "best.depth.onnx") != sha256_file(
        SHIPPED_MODEL.with_name("rebar_keypoint.depth.onnx")
    )
