from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from rebar_data.config import ConfigError
from rebar_data.perception.inference import detector as infer
from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.networks import eager
from rebar_data.perception.networks.files import export_onnx, load_checkpoint, save_checkpoint
from rebar_data.perception.networks.keypoint_net import KeypointNet, ModelConfig
from tests.perception.conftest import TINY_MODEL


@pytest.fixture
def tiny_net():
    torch.manual_seed(0)
    net = KeypointNet(ModelConfig(**TINY_MODEL))
    with torch.no_grad():  # give batch norm non-trivial statistics, so the export has something to get wrong
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
    return net.eval()


def test_onnx_export_gives_the_same_output_as_pytorch(tiny_net, tmp_path):
    rgb = np.random.default_rng(0).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    path = export_onnx(tiny_net, tmp_path / "m.onnx", {"note": "test"})
    onnx_det = Detector.load(path, threads=1, runtime="onnxruntime", reading="single")  # the export itself
    torch_det = eager.detector(tiny_net)
    camera = (100.0, 100.0, 64.0, 48.0)
    np.testing.assert_allclose(onnx_det.raw(rgb, camera=camera), torch_det.raw(rgb, camera=camera), atol=1e-4)
    assert onnx_det.meta["note"] == "test" and onnx_det.backend == "onnxruntime"


def test_detect_pads_any_size_and_returns_points_inside(tiny_net):
    det = eager.detector(tiny_net)
    rgb = np.random.default_rng(1).integers(0, 256, (101, 131, 3), dtype=np.uint8)
    assert det.raw(rgb).shape == (3, 26, 33)
    out = det.detect(rgb, threshold=0.01)
    assert out.ndim == 2 and out.shape[1] == 3
    assert ((out[:, 0] >= 0) & (out[:, 0] < 131) & (out[:, 1] >= 0) & (out[:, 1] < 101)).all()
    assert np.all(np.diff(out[:, 2]) <= 0)  # best first


def test_a_detection_next_to_a_better_one_is_dropped():
    det = np.array(
        [
            [10.0, 10.0, 0.9],
            [12.0, 11.0, 0.8],  # 2.2 px from the best: the same crossing
            [14.5, 10.0, 0.7],  # 4.5 px from the best, 2.7 from the dropped one: a crossing of its own
            [10.0, 12.9, 0.6],  # 2.9 px from the best
            [30.0, 30.0, 0.5],
        ]
    )
    kept = infer.drop_duplicates(det, 3.0)
    np.testing.assert_array_equal(kept, det[[0, 2, 4]])
    assert len(infer.drop_duplicates(det[:1], 3.0)) == 1 and len(infer.drop_duplicates(det[:0], 3.0)) == 0


def test_checkpoint_round_trip(tiny_net, tmp_path):
    save_checkpoint(tmp_path / "m.pt", tiny_net, {"epoch": 3})
    net, meta, _ = load_checkpoint(tmp_path / "m.pt")
    assert meta == {"epoch": 3} and net.cfg == tiny_net.cfg
    x = torch.rand(1, 3, 32, 32) * 255
    rays = torch.zeros(1, 2, 8, 8)
    torch.testing.assert_close(net(x, rays), tiny_net(x, rays))
    # the one loader reads a checkpoint too, through training's reader (READERS), in PyTorch
    det = Detector.load(tmp_path / "m.pt", reading="single", resample=False)
    assert det.backend == "torch" and det.reading == "single" and not det.resample


def test_load_names_what_is_wrong(tmp_path, monkeypatch):
    monkeypatch.setattr(infer, "SHIPPED_MODEL", tmp_path / "none.onnx")
    with pytest.raises(ConfigError, match="no shipped detector"):
        Detector.load()
    with pytest.raises(ConfigError, match="no such model file"):
        Detector.load(tmp_path / "missing.onnx")
    (tmp_path / "weights.bin").write_bytes(b"x")
    with pytest.raises(ConfigError, match=r"\.onnx or \.pt"):
        Detector.load(tmp_path / "weights.bin")
    with pytest.raises(ConfigError, match="holds none of"):
        Detector.load(tmp_path)
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match="cannot be read"):
        Detector.load(tmp_path / "bad.pt")


def test_detect_rejects_what_is_not_an_rgb_image(tiny_net):
    det = eager.detector(tiny_net)
    with pytest.raises(ConfigError, match="RGB array"):
        det.detect(np.zeros((32, 32), np.uint8))
    with pytest.raises(ConfigError, match="threshold"):
        det.detect(np.zeros((32, 32, 3), np.uint8), threshold=1.5)


def test_shipped_model_detects_the_crossings_of_a_freshly_rendered_frame(rendered_frame):
    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    from rebar_data.perception.evaluation.metrics import Truth, pixel_metrics

    rgb, truth, box, camera = rendered_frame
    assert len(truth) >= 20
    det = Detector.load(threads=1).detect(rgb, camera=camera)
    px = pixel_metrics([Truth(truth, box)], [det])
    assert px.recall >= 0.95 and px.precision >= 0.95, (px.recall, px.precision)
    assert px.pck[2.0] >= 0.9 and px.median_px < 1.0, (px.pck, px.median_px)


def test_a_model_file_of_format_1_names_the_release_that_reads_it(tmp_path):
    """Format 2 is the one this code reads; an older file is one line naming rebar-data 0.1.0."""
    import onnx

    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    model = onnx.load(str(infer.SHIPPED_MODEL))
    entry = next(e for e in model.metadata_props if e.key == model_file.META_KEY)
    entry.value = json.dumps({**json.loads(entry.value), "format_version": 1})
    old = tmp_path / infer.SHIPPED_MODEL.name
    onnx.save(model, str(old))
    with pytest.raises(ConfigError, match=r"format 1, which rebar-data 0\.1\.0 reads; accepted: format 2"):
        Detector.load(old)


def test_a_model_file_reads_its_first_pass_in_its_stored_views():
    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    meta = Detector.load(threads=1).meta
    entry = meta["refiner"] | {"views": 4}
    stored = model_file.load_stages(
        infer.SHIPPED_MODEL, {**meta, "refiner": {**entry, "first_pass_views": 1}}, 1, "onnxruntime"
    )[0]
    assert stored.views == 4 and stored.first_pass_views == 1


def test_the_later_passes_skip_only_detections_that_cannot_reach_the_threshold(monkeypatch):
    """Without a line check, the detector spares the second stage's later passes for the detections its
    verification has put out of reach of the threshold (with or without depth); what it returns is what it
    returns without sparing them, at the operating point and at a low threshold."""
    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    from tests.perception.synthetic import drawn_frame

    det = Detector.load(threads=1)
    det.line_check = None
    rgb, depth = drawn_frame()  # dense with bars on the ground: many candidates the later stages reject
    first_pass, later_passes = det.refiner.first_pass, det.refiner.later_passes
    spared, first = [], {}

    def kept_first(image, uv, *, mirrored):
        first["uv"], _, first["box"] = out = first_pass(image, uv, mirrored=mirrored)
        return out

    def counted(image, uv, box, *, mirrored):
        spared.append(len(first["uv"]) - len(uv))
        return later_passes(image, uv, box, mirrored=mirrored)

    def all_moved(image, uv, box, *, mirrored):  # every point moved; those asked for returned
        moved = later_passes(image, first["uv"], first["box"], mirrored=mirrored)
        row = {tuple(p): k for k, p in enumerate(first["uv"])}
        return moved[[row[tuple(p)] for p in uv]]

    monkeypatch.setattr(det.refiner, "first_pass", kept_first)
    for threshold in (0.5, 0.05):
        for d in (depth, None):
            monkeypatch.setattr(det.refiner, "later_passes", counted)
            got = det.detect(rgb, depth=d, threshold=threshold)
            monkeypatch.setattr(det.refiner, "later_passes", all_moved)
            np.testing.assert_array_equal(got, det.detect(rgb, depth=d, threshold=threshold))
    assert spared[0] > 0  # at the operating point some really were spared


def test_an_onnx_file_turns_back_into_the_network_it_was_exported_from(tiny_net, tmp_path):
    from rebar_data.perception.networks.files import network_from_onnx

    rgb = np.random.default_rng(2).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    path = export_onnx(tiny_net, tmp_path / "m.onnx", {"note": "back"})
    net, meta = network_from_onnx(path)
    assert meta == {"note": "back"} and net.cfg == tiny_net.cfg
    camera = (100.0, 100.0, 64.0, 48.0)
    want = eager.detector(tiny_net).raw(rgb, camera=camera)
    np.testing.assert_allclose(eager.detector(net).raw(rgb, camera=camera), want, atol=1e-4)
    # and it exports again to the same outputs: the round trip loses nothing
    again = Detector.load(
        export_onnx(net, tmp_path / "again.onnx", meta), threads=1, runtime="onnxruntime", reading="single"
    )
    np.testing.assert_allclose(again.raw(rgb, camera=camera), want, atol=1e-4)


def test_a_file_without_detector_metadata_is_refused(tmp_path):
    import onnx

    from rebar_data.perception.networks.files import network_from_onnx

    bare = tmp_path / "bare.onnx"
    onnx.save(onnx.helper.make_model(onnx.helper.make_graph([], "g", [], [])), str(bare))
    with pytest.raises(ConfigError, match="carries no detector metadata"):
        network_from_onnx(bare)
    (tmp_path / "junk.onnx").write_bytes(b"not onnx")
    with pytest.raises(ConfigError, match="cannot be read as an ONNX file"):
        network_from_onnx(tmp_path / "junk.onnx")


def test_every_reader_the_run_time_names_is_there():
    """The readers :data:`~.detector.READERS` names by string exist: a rename breaks this test, not a user's
    call (tests/integration/test_imports.py checks that loading an .onnx file imports none of them)."""
    import importlib

    for suffix, name in infer.READERS.items():
        module, _, function = name.partition(":")
        assert callable(getattr(importlib.import_module(module), function)), suffix
