"""The second stage's later passes read by an int8 copy of it (``RefineConfig.quantize = "later"``): the
first pass, whose verification every score counts, stays in float."""

from __future__ import annotations

import numpy as np
import pytest

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import load_split, read_sample_image
from rebar_data.perception.inference import detector as infer
from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.inference.model_file import int8_passes_path
from rebar_data.perception.inference.refine import Refiner
from rebar_data.perception.networks.files import onnx_meta
from tests.perception.conftest import refined, shipped_model_copy


def _network(offset: float, logit: float, calls: list[str], name: str):
    """A stand-in network: every patch's offset (du, dv) = (offset, 0), the given logit, log box side 0."""

    def run(x: np.ndarray) -> np.ndarray:
        calls.append(name)
        out = np.zeros((len(x), 4), np.float32)
        out[:, 0], out[:, 2] = offset, logit
        return out

    return run


def test_the_later_passes_read_the_int8_copy_and_the_first_pass_the_float_file():
    calls: list[str] = []
    refiner = Refiner(
        _network(0.0, 1.5, calls, "float"),
        patch_px=16,
        iterations=3,
        verifies=True,
        views=1,
        step=0.5,
        int8_run=_network(2.0, -9.0, calls, "int8"),
    )
    assert refiner.int8_run is not None
    image = np.zeros((64, 64, 3), np.uint8)
    uv, logit = refined(refiner, image, np.array([[20.0, 30.0]]))
    assert calls == ["float", "int8", "int8"]
    np.testing.assert_allclose(logit, [1.5])  # the float file's verification
    # the first pass puts it on its patch's corner (20, 30); each later one half way to its patch's corner
    # + 2 (u: 20 -> 21 -> 22)
    np.testing.assert_allclose(uv, [[22.0, 30.0]])
    calls.clear()
    refiner.int8_run = None  # the float file for every pass, as a model without the copy
    uv, _ = refined(refiner, image, np.array([[20.0, 30.0]]))
    assert calls == ["float"] * 3
    np.testing.assert_allclose(uv, [[20.0, 30.0]])
    assert Refiner(_network(0, 0, [], "f"), patch_px=16, iterations=2, verifies=True).int8_run is None


def test_the_detector_reads_its_later_passes_with_the_int8_copy(drawn_dataset, tmp_path):
    from rebar_data.perception.training.card import stage_rows

    model = shipped_model_copy(tmp_path)
    out = model_file.int8_passes_path(model)
    assert out.is_file() and out.stat().st_size < model.stat().st_size
    assert onnx_meta(model)["refiner"]["quantize"] == "later"
    det = Detector.load(model, threads=1, reading="single")  # the first pass in float (the mirrored: int8)
    assert det.refiner.int8_run is not None
    assert ("second stage, int8 copy", f"`{out.name}`") in [row[:2] for row in stage_rows(model, det, {})]
    moved = []
    for s in load_split(drawn_dataset, "test"):
        rgb = read_sample_image(s)
        with_int8 = det.detect(rgb, camera=s.camera, threshold=0.05)
        int8_run, det.refiner.int8_run = det.refiner.int8_run, None
        in_float = det.detect(rgb, camera=s.camera, threshold=0.05)
        det.refiner.int8_run = int8_run
        # the same detections, scored alike (the float file verifies them), placed nearly alike
        np.testing.assert_array_equal(with_int8[:, 2], in_float[:, 2])
        moved.append(np.abs(with_int8[:, :2] - in_float[:, :2]).max(initial=0.0))
    assert max(moved) < 0.5, moved
    # the copy is checked as every stage is: missing, or not the file the model names
    keep = out.read_bytes()
    out.write_bytes(keep[:-1] + b"\0")
    with pytest.raises(ConfigError, match="SHA-256"):
        Detector.load(model)
    out.unlink()
    with pytest.raises(ConfigError, match="refine.int8.onnx is missing"):
        Detector.load(model)


def test_the_shipped_files_stay_within_five_megabytes():
    """The issue's size goal: every file the shipped model loads, the int8 copy included."""
    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    files = sorted(infer.MODELS_DIR.glob(f"{infer.SHIPPED_MODEL.stem}*.onnx"))
    det = Detector.load(None, threads=1)
    loaded = [infer.SHIPPED_MODEL, model_file.refiner_path(infer.SHIPPED_MODEL)]
    loaded += [int8_passes_path(infer.SHIPPED_MODEL)] if det.refiner.int8_run is not None else []
    assert set(loaded) <= set(files)
    assert sum(f.stat().st_size for f in files) <= 5_000_000, [(f.name, f.stat().st_size) for f in files]
