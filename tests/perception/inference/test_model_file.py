from __future__ import annotations

import numpy as np
import pytest

from rebar_data.config import ConfigError
from rebar_data.perception.inference import detector as infer
from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.inference.model_file import (
    OpenVinoSession,
    onnx_session,
    openvino_bf16,
    resolve_runtime,
)

needs_openvino = pytest.mark.skipif(
    model_file._openvino_core() is None, reason="openvino is not installed (pip install openvino)"
)


def test_a_runtime_is_one_of_the_accepted_names_and_auto_follows_the_cpu():
    with pytest.raises(ConfigError, match="runtime 'tensorrt' is not accepted; accepted: auto, onnxruntime"):
        resolve_runtime("tensorrt")
    assert resolve_runtime("onnxruntime") == "onnxruntime"
    assert resolve_runtime("auto") == ("openvino" if openvino_bf16() else "onnxruntime")


def test_openvino_is_refused_with_a_clear_message_where_it_is_not_installed(monkeypatch):
    monkeypatch.setattr(model_file, "_openvino_core", lambda: None)
    assert resolve_runtime("auto") == "onnxruntime"
    with pytest.raises(ConfigError, match="needs the openvino package; accepted: pip install openvino"):
        resolve_runtime("openvino")


@needs_openvino
def test_an_openvino_session_answers_as_onnx_runtime_does(trained_run):
    model = trained_run.out_dir / "best.onnx"
    ort, ov = onnx_session(model, 1), onnx_session(model, 1, "openvino")
    assert isinstance(ov, OpenVinoSession)
    assert ov.get_modelmeta().custom_metadata_map == ort.get_modelmeta().custom_metadata_map
    assert [(a.name, a.shape) for a in ov.get_inputs()] == [(a.name, a.shape) for a in ort.get_inputs()]
    rng = np.random.default_rng(0)
    for h, w in ((64, 96), (96, 64), (64, 96)):  # two image sizes: each compiled for its own
        feed = {
            "image": rng.integers(0, 256, (1, h, w, 3), dtype=np.uint8),
            "rays": rng.normal(size=(1, 2, h // 4, w // 4)).astype(np.float32),
        }
        want, got = ort.run(None, feed)[0], ov.run(None, feed)[0]
        assert got.shape == want.shape == (1, 3, h // 4, w // 4)
        # bfloat16 keeps 8 bits of mantissa: logits agree to a few hundredths of their spread
        tolerance = 0.05 if openvino_bf16() else 1e-4
        assert np.abs(got - want).max() <= tolerance * max(1.0, np.abs(want).max()), np.abs(got - want).max()
    assert len(ov._compiled) == 2
    # past SHAPES_KEPT sizes, one compile with the sizes left free serves the rest
    for k in range(model_file.SHAPES_KEPT + 2):
        h, w = 32 * (k + 1), 64
        feed = {
            "image": rng.integers(0, 256, (1, h, w, 3), dtype=np.uint8),
            "rays": rng.normal(size=(1, 2, h // 4, w // 4)).astype(np.float32),
        }
        want, got = ort.run(None, feed)[0], ov.run(None, feed)[0]
        assert got.shape == want.shape
        assert np.abs(got - want).max() <= tolerance * max(1.0, np.abs(want).max())
    assert len(ov._compiled) == model_file.SHAPES_KEPT + 1 and () in ov._compiled
    # that compile also takes a batch of two (a frame and its mirror image in the mirrored reading)
    h, w = 48, 80
    feed = {
        "image": rng.integers(0, 256, (2, h, w, 3), dtype=np.uint8),
        "rays": rng.normal(size=(2, 2, h // 4, w // 4)).astype(np.float32),
    }
    both = ov.run(None, feed)[0]
    assert both.shape == (2, 3, h // 4, w // 4)
    for i in range(2):
        alone = ov.run(None, {k: v[i : i + 1] for k, v in feed.items()})[0]
        assert np.abs(both[i : i + 1] - alone).max() <= tolerance * max(1.0, np.abs(alone).max())


@needs_openvino
def test_openvino_reads_a_frame_and_its_mirror_image_in_one_call_with_the_same_numbers():
    """The mirrored reading's two first-stage reads go through OpenVINO as one batch of two; ONNX Runtime,
    whose files take one image, reads them in two calls. The batch gives what the two calls give."""
    from tests.perception.synthetic import drawn_frame

    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    det = Detector.load(threads=2, runtime="openvino")
    assert det._run_pair is not None
    assert Detector.load(threads=2, runtime="onnxruntime")._run_pair is None
    pairs: list[tuple[int, ...]] = []
    run_pair = det._run_pair

    def counted(images: np.ndarray, rays: np.ndarray) -> np.ndarray:
        pairs.append(images.shape)
        return run_pair(images, rays)

    rgb, _ = drawn_frame()
    for width in (640, 627):  # 627 is padded to whole blocks before the mirror image is made
        image = np.ascontiguousarray(rgb[:, :width])
        det._run_pair = counted
        one_call = det.raw(image)
        det._run_pair = None
        two_calls = det.raw(image)
        assert one_call.shape == two_calls.shape == (3, 120, -(-width // 4))
        # the same kernels per image here (measured: equal to the bit); a hair of room for another CPU's
        np.testing.assert_allclose(one_call, two_calls, atol=1e-3)
    assert pairs == [(2, 480, 640, 3)] * 2


@needs_openvino
def test_a_batch_of_patches_is_padded_for_openvino_and_comes_back_as_long():
    path = model_file.refiner_path(infer.SHIPPED_MODEL)
    if not path.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    ort, ov = onnx_session(path, 1), onnx_session(path, 1, "openvino")
    assert isinstance(ov, OpenVinoSession)
    size = ort.get_inputs()[0].shape[1:]
    rng = np.random.default_rng(1)
    for n in (1, 5, 8, 13):
        x = rng.integers(0, 256, (n, *size), dtype=np.uint8)
        want, got = ort.run(None, {"patches": x})[0], ov.run(None, {"patches": x})[0]
        assert got.shape == want.shape and len(got) == n
        assert np.abs(got - want).max() <= 0.05 * max(1.0, np.abs(want).max())
    assert ov.run(None, {"patches": np.zeros((0, *size), np.uint8)})[0].shape == (0, 4)
    # one session called from threads at once gives what it gives called in turn
    from concurrent.futures import ThreadPoolExecutor

    batches = [rng.integers(0, 256, (n, *size), dtype=np.uint8) for n in (3, 9, 17, 30)]
    alone = [ov.run(None, {"patches": x})[0] for x in batches]
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda x: ov.run(None, {"patches": x})[0], batches))
    for a, b in zip(alone, together, strict=True):
        np.testing.assert_array_equal(a, b)


@needs_openvino
def test_an_int8_file_runs_in_onnx_runtime_whatever_the_runtime(trained_run):
    # the tests' tiny run writes the int8 copy its second stage's later passes read, which OpenVINO does not read
    path = model_file.int8_passes_path(trained_run.out_dir / "best.onnx")
    assert not isinstance(onnx_session(path, 1, "openvino"), OpenVinoSession)
    with pytest.raises(ConfigError, match="cannot be loaded as an ONNX model"):
        onnx_session(trained_run.out_dir / "config.json", 1, "openvino")


@needs_openvino
def test_the_shipped_detector_finds_the_same_crossings_in_either_runtime():
    from tests.perception.synthetic import drawn_frame

    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    det_ort = Detector.load(threads=1, runtime="onnxruntime")
    det_ov = Detector.load(threads=1, runtime="openvino")
    assert (det_ort.backend, det_ov.backend) == ("onnxruntime", "openvino")
    rgb, _ = drawn_frame()
    a, b = det_ort.detect(rgb, threshold=0.3), det_ov.detect(rgb, threshold=0.3)
    # every confident detection of the one is a detection of the other, placed within half a pixel
    for p, q in ((a, b), (b, a)):
        confident = p[p[:, 2] >= 0.6]
        assert len(confident) >= 20
        gap = np.hypot(*(confident[:, None, :2] - q[None, :, :2]).transpose(2, 0, 1)).min(axis=1)
        assert gap.max() < 0.5, gap.max()


def test_the_shipped_model_loads_in_onnx_runtime_and_in_the_default_runtime():
    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    assert Detector.load(runtime="onnxruntime").backend == "onnxruntime"
    assert Detector.load().backend == resolve_runtime("auto")
