"""Detector latency (``rebar bench``): 640x480 paper-tunnel frames rendered along its pipeline's camera
trajectories, batch 1, two CPU threads, end to end, against the same network in eager PyTorch."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

FRAME_HW = (480, 640)
BENCH_THREADS = 2
BUDGET_MS = 15.0  # a 31 Hz servo loop leaves 32 ms a step; the detector may take under half
RENDERED_FRAMES = 8
BenchFrame = tuple[np.ndarray, np.ndarray | None]  # RGB (H, W, 3) uint8 and its depth (H, W) metres, 0 = none


def runtime_description(runtime: str) -> str:
    """How ``runtime`` runs here, in words (for the bench, the model card and `rebar score`)."""
    from rebar_data.perception.inference import model_file

    if model_file.resolve_runtime(runtime) == "onnxruntime":
        return "ONNX Runtime, float32"
    return f"OpenVINO, {'bfloat16' if model_file.openvino_bf16() else 'float32'}"


def _time_ms(fn: Callable[[], object], *, repeats: int, warmup: int = 5) -> np.ndarray:
    for _ in range(warmup):
        fn()
    out = np.empty(repeats)
    for i in range(repeats):
        t = time.perf_counter()
        fn()
        out[i] = (time.perf_counter() - t) * 1e3
    return out


def rendered_frames(count: int = RENDERED_FRAMES, *, seed: int = 0) -> list[BenchFrame]:
    """``count`` paper-tunnel frames at 640x480 (Kinect v1 intrinsics), each under a new scene and sensor."""
    from rebar_data.config import PAPER_PIPELINE
    from rebar_data.geometry.build import build_rebar_mesh
    from rebar_data.pipeline import load_pipeline
    from rebar_data.render.renderer import Renderer
    from rebar_data.scene.cameras import PRESETS, trajectory_poses
    from rebar_data.scene.sample import sample_scene, sample_sensor

    cfg = load_pipeline(PAPER_PIPELINE)
    rm = build_rebar_mesh(cfg.mesh_config())
    rng = np.random.default_rng(seed)
    renderer = Renderer(PRESETS["kinect_v1"], cfg.render)
    try:
        renderer.set_mesh(rm)
        frames = []
        for i in range(count):
            traj = cfg.camera.trajectories[i % len(cfg.camera.trajectories)]
            renderer.set_scene(sample_scene(cfg.scene, rng))
            pose = trajectory_poses(traj, rm, rng)[rng.integers(traj.frames)]
            rendered = renderer.render(pose, sample_sensor(cfg.scene, rng), rng)
            frames.append((rendered.rgb, rendered.depth_m))
    finally:
        renderer.close()
    return frames


def latency_frames() -> tuple[list[BenchFrame], str]:
    """The frames latency is measured on, and what they are."""
    return rendered_frames(), f"{RENDERED_FRAMES} rendered paper-tunnel frames"


@dataclass
class DetectorLatency:
    """End-to-end latency over frames (median, 90th percentile), the first stage's candidates and the
    crossings returned a frame, and for a model with later stages the median of the first stage alone."""

    median_ms: float
    p90_ms: float
    frames: int
    candidates: float
    crossings: float
    first_stage_ms: float | None = None

    @property
    def second_stage_us_per_candidate(self) -> float | None:
        if self.first_stage_ms is not None:
            return 1e3 * (self.median_ms - self.first_stage_ms) / max(self.candidates, 1.0)


def detector_latency(det, frames: list[BenchFrame], *, repeats: int) -> DetectorLatency:
    """Time ``det.detect`` on ``frames`` with their depth (``repeats`` calls in all), and right after each
    frame its first stage alone when it has later ones."""
    from rebar_data.perception.evaluation.evaluate import first_stage_only

    each = max(3, -(-repeats // len(frames)))
    two_stages = det.refiner is not None or det.depth_check is not None
    ours, first, kept, candidates = [], [], [], []
    for rgb, depth in frames:

        def call(rgb=rgb, depth=depth):
            return det.detect(rgb, depth=depth)

        ours.append(_time_ms(call, repeats=each, warmup=2))
        kept.append(len(call()))
        with first_stage_only(det):
            if two_stages:
                first.append(_time_ms(call, repeats=each, warmup=2))
            candidates.append(len(call()))
    ours = np.concatenate(ours)
    return DetectorLatency(
        median_ms=float(np.median(ours)),
        p90_ms=float(np.percentile(ours, 90)),
        frames=len(frames),
        candidates=float(np.mean(candidates)),
        crossings=float(np.mean(kept)),
        first_stage_ms=float(np.median(np.concatenate(first))) if two_stages else None,
    )


def run(repeats: int = 100) -> list[str]:
    """Lines to print: the shipped detector's latency and its network's in eager PyTorch."""
    import torch

    from rebar_data.camera import Intrinsics
    from rebar_data.perception.inference.detector import Detector, first_stage_rays
    from rebar_data.perception.networks.keypoint_net import KeypointNet, ModelConfig

    threads_before = torch.get_num_threads()
    torch.set_num_threads(BENCH_THREADS)
    try:
        frames, described = latency_frames()
        load = " / ".join(f"{x:.2f}" for x in os.getloadavg())
        lines = [f"perception: load average {load} on {os.cpu_count()} cores"]
        det = Detector.load(None, threads=BENCH_THREADS)
        lat = detector_latency(det, frames, repeats=repeats)
        med = lat.median_ms
        lines.append(
            f"perception: shipped detector, {runtime_description('auto')}, {det.reading} reading, "
            f"{BENCH_THREADS} threads, 640x480, end to end over {described}: median {med:.1f} ms, "
            f"p90 {lat.p90_ms:.1f} ms "
            f"({lat.crossings:.0f} crossings a frame; budget {BUDGET_MS:g} ms: "
            f"{'met' if med <= BUDGET_MS else 'MISSED'})"
        )
        if lat.first_stage_ms is not None:
            lines.append(
                f"perception:   of which the first stage {lat.first_stage_ms:.1f} ms and the later ones "
                f"({lat.candidates:.0f} candidates a frame) {med - lat.first_stage_ms:.1f} ms, "
                f"{lat.second_stage_us_per_candidate:.0f} us a candidate"
            )
        if det.depth_check is not None:
            rgb_only = detector_latency(det, [(rgb, None) for rgb, _ in frames], repeats=repeats)
            lines.append(
                f"perception:   without depth: median {rgb_only.median_ms:.1f} ms, p90 "
                f"{rgb_only.p90_ms:.1f} ms ({rgb_only.median_ms / med:.2f}x the call with depth)"
            )
        if det.zoom is not None:  # a frame whose crossings are seen small or large is read twice
            zoom, det.zoom = det.zoom, None
            once = detector_latency(det, frames, repeats=repeats)
            det.zoom = zoom
            lines.append(
                f"perception:   every frame read once (--no-zoom): median {once.median_ms:.1f} ms "
                f"({med / once.median_ms:.2f}x that with the zoom)"
            )
        net = KeypointNet(ModelConfig()).eval()
        x = torch.from_numpy(frames[0][0]).permute(2, 0, 1)[None].float()
        camera = Intrinsics(FRAME_HW[1], FRAME_HW[0], 525.0, 525.0, 320.0, 240.0)
        rays = torch.from_numpy(first_stage_rays(camera))[None]
        with torch.inference_mode():
            eager = _time_ms(lambda: net(x, rays), repeats=max(10, repeats // 5))
        reference = lat.first_stage_ms or med
        lines.append(
            f"perception: same network in eager PyTorch (forward only): median {np.median(eager):.1f} ms "
            f"({np.median(eager) / reference:.1f}x our first stage with peaks, end to end)"
        )
        return lines
    finally:
        torch.set_num_threads(threads_before)
