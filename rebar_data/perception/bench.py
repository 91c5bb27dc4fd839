"""Detector latency: one 640x480 frame, batch 1, on two CPU threads, end to end (padding, network,
peak decoding), against references measured in the same run: the same network in eager PyTorch and a
YOLOv8n-pose-shaped network on the same runtime."""

from __future__ import annotations

import os
import tempfile
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FRAME_HW = (480, 640)
THREADS = 2
BUDGET_MS = 15.0  # a 31 Hz servo loop leaves 32 ms a step; the detector may take under half


def _time_ms(fn: Callable[[], object], *, repeats: int, warmup: int = 5) -> np.ndarray:
    for _ in range(warmup):
        fn()
    out = np.empty(repeats)
    for i in range(repeats):
        t = time.perf_counter()
        fn()
        out[i] = (time.perf_counter() - t) * 1e3
    return out


def _frame() -> np.ndarray:
    """A drawn rebar frame of 640x480, so decoding sees a realistic number of peaks."""
    from rebar_data.perception.synthetic import SyntheticSpec, random_frame

    spec = SyntheticSpec(width=FRAME_HW[1], height=FRAME_HW[0], focal_px=525.0, occluder_fraction=0.0)
    rng = np.random.default_rng(0)
    return random_frame(spec, rng)[0]


@dataclass
class DetectorLatency:
    """A detector's end-to-end latency on one frame: median and 90th percentile, the crossings it found,
    and (for a two-stage model) the median with the first stage alone."""

    median_ms: float
    p90_ms: float
    crossings: int
    first_stage_ms: float | None = None

    @property
    def second_stage_us_per_crossing(self) -> float | None:
        if self.first_stage_ms is None:
            return None
        return 1e3 * (self.median_ms - self.first_stage_ms) / max(self.crossings, 1)


def detector_latency(det, *, repeats: int, rgb: np.ndarray | None = None) -> DetectorLatency:
    """Time ``det.detect`` on ``rgb`` (default: the drawn 640x480 benchmark frame), and its first stage
    alone when it has a second."""
    rgb = _frame() if rgb is None else rgb
    ours = _time_ms(lambda: det.detect(rgb), repeats=repeats)
    first = None
    if det.refiner is not None:
        with det.first_stage_only():
            first = float(np.median(_time_ms(lambda: det.detect(rgb), repeats=repeats)))
    return DetectorLatency(
        float(np.median(ours)), float(np.percentile(ours, 90)), len(det.detect(rgb)), first
    )


def _onnx_session_ms(net, example, *, repeats: int) -> np.ndarray:
    import onnxruntime as ort
    import torch

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.onnx"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(
                net.eval(), (example,), str(path), input_names=["x"], opset_version=17, dynamo=False
            )
        so = ort.SessionOptions()
        so.intra_op_num_threads, so.inter_op_num_threads = THREADS, 1
        so.log_severity_level = 3
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")  # as the detector runs
        sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    x = example.numpy()
    return _time_ms(lambda: sess.run(None, {"x": x}), repeats=repeats)


def run(repeats: int = 100) -> list[str]:
    """Lines to print: latency of the shipped (or an untrained) detector and of the references."""
    import torch

    from rebar_data.perception.baseline import YoloPoseLike
    from rebar_data.perception.config import ModelConfig
    from rebar_data.perception.infer import SHIPPED_MODEL, Detector
    from rebar_data.perception.model import KeypointNet, count_parameters, ray_grid

    threads_before = torch.get_num_threads()
    torch.set_num_threads(THREADS)
    try:
        rgb = _frame()
        load = os.getloadavg()
        lines = [
            f"perception: load average {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} (1 / 5 / 15 min) on "
            f"{os.cpu_count()} cores when the timing started"
        ]
        if SHIPPED_MODEL.exists():
            det, what = Detector.load(None, threads=THREADS), "shipped detector"
        else:
            from rebar_data.perception.export import export_onnx

            tmp = Path(tempfile.mkdtemp())
            torch.manual_seed(0)
            export_onnx(KeypointNet(ModelConfig()), tmp / "untrained.onnx", {})
            det, what = (
                Detector.load(tmp / "untrained.onnx", threads=THREADS),
                "untrained detector (none shipped yet)",
            )
        lat = detector_latency(det, repeats=repeats, rgb=rgb)
        med, n = lat.median_ms, lat.crossings
        lines.append(
            f"perception: {what}, ONNX Runtime, {THREADS} threads, 640x480 batch 1, end to end: "
            f"median {med:.1f} ms, p90 {lat.p90_ms:.1f} ms a frame ({1e3 / med:.0f} Hz; "
            f"{n} crossings found; budget {BUDGET_MS:g} ms: {'met' if med <= BUDGET_MS else 'MISSED'})"
        )
        if lat.first_stage_ms is not None:  # what the second stage costs on this frame's crossings
            lines.append(
                f"perception: of which the first stage (heatmap network and peaks) {lat.first_stage_ms:.1f} ms "
                f"and the second (refining {n} crossings) {med - lat.first_stage_ms:.1f} ms, "
                f"{lat.second_stage_us_per_crossing:.0f} us a crossing"
            )
        net = KeypointNet(ModelConfig()).eval()
        x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float()
        rays = torch.from_numpy(ray_grid(*FRAME_HW, (525.0, 525.0, 320.0, 240.0)))[None]  # output cells
        with torch.inference_mode():
            eager = _time_ms(lambda: net(x, rays), repeats=max(10, repeats // 5))
        lines.append(
            f"perception: same network in eager PyTorch (forward only): median {np.median(eager):.1f} ms "
            f"({np.median(eager) / med:.1f}x the ONNX Runtime figure)"
        )
        yolo = YoloPoseLike().eval()
        yolo_x = (x / 255.0).contiguous()
        yolo_ms = _onnx_session_ms(yolo, yolo_x, repeats=max(10, repeats // 5))
        lines.append(
            f"perception: YOLOv8n-pose-shaped network ({count_parameters(yolo) / 1e6:.1f} M parameters vs "
            f"{count_parameters(net) / 1e3:.0f} k), same runtime, forward only: median {np.median(yolo_ms):.1f} ms "
            f"({np.median(yolo_ms) / med:.1f}x ours)"
        )
        return lines
    finally:
        torch.set_num_threads(threads_before)
