"""Detector latency: 640x480 frames, batch 1, on two CPU threads, end to end (padding, network, peak
decoding, second stage, depth check), against references measured in the same run: the same network in eager PyTorch
and a YOLOv8n-pose-shaped network on the same runtime.

The frames are like the training data's, at the servo camera's size: paper-tunnel's mesh rendered at 640x480
from its pipeline's camera trajectories, each under another scene drawn from its scene settings
(:func:`rendered_frames`). The second stage's time grows with the first stage's candidates, so a
drawn frame dense with bars (about 160 candidates, where rendered frames have 30-90) is timed as well, as
the worst case; it is also what is timed when the renderer cannot start.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FRAME_HW = (480, 640)
THREADS = 2
BUDGET_MS = 15.0  # a 31 Hz servo loop leaves 32 ms a step; the detector may take under half
RENDERED_FRAMES = 8
Frame = tuple[np.ndarray, np.ndarray]  # RGB (H, W, 3) uint8 and its depth (H, W) float32 metres, 0 = none


def _time_ms(fn: Callable[[], object], *, repeats: int, warmup: int = 5) -> np.ndarray:
    for _ in range(warmup):
        fn()
    out = np.empty(repeats)
    for i in range(repeats):
        t = time.perf_counter()
        fn()
        out[i] = (time.perf_counter() - t) * 1e3
    return out


def _in_turn(
    frames: list[np.ndarray],
    *,
    repeats: int,
    on: Callable[[np.ndarray], object],
    off: Callable[[np.ndarray], object],
) -> tuple[float, float]:
    """Median ms of ``on(rgb)`` and of ``off(rgb)`` on ``frames``, timed in turn call by call (this machine
    changes speed between runs; the two see it in the same state)."""
    each = max(3, -(-repeats // len(frames)))
    on_ms, off_ms = [], []
    for rgb in frames:
        for _ in range(each):
            on_ms.append(_time_ms(lambda rgb=rgb: on(rgb), repeats=1, warmup=1)[0])
            off_ms.append(_time_ms(lambda rgb=rgb: off(rgb), repeats=1, warmup=1)[0])
    return float(np.median(on_ms)), float(np.median(off_ms))


def _switched(
    det,
    frames: list[np.ndarray],
    *,
    repeats: int,
    switch: Callable[[bool], None],
    depth: dict[int, np.ndarray] | None = None,
) -> tuple[float, float]:
    """:func:`_in_turn` of ``det.detect`` with ``switch(True)`` and with ``switch(False)``, without depth
    (``depth`` None) or with ``depth[id(rgb)]``; ``switch(True)`` again at the end."""

    def with_switch(on: bool) -> Callable[[np.ndarray], object]:
        def detect(rgb: np.ndarray) -> object:
            switch(on)
            return det.detect(rgb, depth=None if depth is None else depth[id(rgb)])

        return detect

    try:
        return _in_turn(frames, repeats=repeats, on=with_switch(True), off=with_switch(False))
    finally:
        switch(True)


def line_check_cost(det, frames: list[np.ndarray], *, repeats: int) -> tuple[float, float]:
    """Median ms of the RGB path with the line check and without it (:func:`_in_turn`)."""
    check = det.line_check
    return _switched(
        det, frames, repeats=repeats, switch=lambda on: setattr(det, "line_check", check if on else None)
    )


def flatten_cost(det, frames: list[tuple[np.ndarray, np.ndarray]], *, repeats: int) -> tuple[float, float]:
    """Median ms of the call with the depth image (``frames``: rgb, depth) with what lies behind flattened
    (``Detector.flatten_behind``; :mod:`~rebar_data.perception.inference.image`) and without, timed in turn
    (:func:`_switched`); the detector is left as it was."""
    with det.flattening():
        return _switched(
            det,
            [rgb for rgb, _ in frames],
            repeats=repeats,
            switch=lambda on: setattr(det, "flatten_behind", on),
            depth={id(rgb): d for rgb, d in frames},
        )


def int8_passes_cost(det, frames: list[np.ndarray], *, repeats: int) -> tuple[float, float]:
    """Median ms of the RGB path with the second stage's later passes read by its int8 copy and by the
    float file (:func:`_in_turn`); the detector must have the copy."""
    return _switched(
        det, frames, repeats=repeats, switch=lambda on: setattr(det.refiner, "use_int8_passes", on)
    )


def reading_cost(det, frames: list[np.ndarray], *, repeats: int) -> tuple[float, float]:
    """Median ms of the RGB path in the mirrored reading and in the single one (``Detector.reading``),
    timed in turn (:func:`_in_turn`); the detector is left in the reading it had."""
    before = det.reading
    try:
        return _switched(
            det,
            frames,
            repeats=repeats,
            switch=lambda on: setattr(det, "reading", "mirrored" if on else "single"),
        )
    finally:
        det.reading = before


def focal_cost(det, frames: list[np.ndarray], *, repeats: int) -> tuple[float, float]:
    """Median ms of the RGB path on ``frames`` (640x480, at the camera ``detect`` assumes for them) enlarged
    twice with their intrinsics, as
    a 1280x960 camera of the same field of view gives them: read at the trained focal length (resampled,
    :mod:`~rebar_data.perception.inference.image`) and as they come, timed in turn (:func:`_in_turn`); the detector
    is left as it was."""
    from rebar_data.perception.inference.image import resample, scaled_camera

    before = det.resample
    large = [resample(rgb, (2 * rgb.shape[0], 2 * rgb.shape[1])) for rgb in frames]
    camera = scaled_camera(det.default_camera(*frames[0].shape[:2]), 2.0, 2.0)  # the frames' own, enlarged

    def read(resampled: bool) -> Callable[[np.ndarray], object]:
        def detect(rgb: np.ndarray) -> object:
            det.resample = resampled
            return det.detect(rgb, camera=camera)

        return detect

    try:
        return _in_turn(large, repeats=repeats, on=read(True), off=read(False))
    finally:
        det.resample = before


def runtime_cost(det, frames: list[np.ndarray], *, repeats: int) -> tuple[float, float]:
    """Median ms of the RGB path of ``det`` (loaded from a file, in OpenVINO) and of its file run by ONNX
    Runtime (:mod:`~rebar_data.perception.inference.model_file`), timed in turn (:func:`_in_turn`)."""
    from rebar_data.perception.inference.detector import Detector

    onnxruntime = Detector.load(det.path, threads=THREADS, runtime="onnxruntime")
    return _in_turn(frames, repeats=repeats, on=det.detect, off=onnxruntime.detect)


def drawn_frame() -> Frame:
    """A drawn rebar frame of 640x480 and its depth, dense with bars: the later stages' worst case."""
    rgb, _, depth = drawn_frame_labelled()
    return rgb, depth


def drawn_frame_labelled() -> tuple[np.ndarray, list[dict], np.ndarray]:
    """:func:`drawn_frame` with its keypoint records (focal length 525 px)."""
    from rebar_data.perception.evaluation.synthetic import SyntheticSpec, random_frame

    spec = SyntheticSpec(width=FRAME_HW[1], height=FRAME_HW[0], focal_px=525.0, occluder_fraction=0.0)
    return random_frame(spec, np.random.default_rng(0))


def rendered_frames(count: int = RENDERED_FRAMES, *, seed: int = 0) -> list[Frame]:
    """``count`` frames like paper-tunnel's, at the servo camera's size: its mesh rendered at 640x480 with the
    Kinect v1 intrinsics, from its pipeline's camera trajectories in turn, each under a new scene (lights,
    material, surroundings) and sensor effects drawn from its settings.

    Raises:
        RuntimeError: and others from Open3D when the offscreen renderer cannot start here.
    """
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


@dataclass
class DetectorLatency:
    """A detector's end-to-end latency over frames: median and 90th percentile of all timed calls, and
    per frame on average the first stage's candidates (what the second stage refines) and the crossings
    returned; for a model with later stages also the median with the first stage alone."""

    median_ms: float
    p90_ms: float
    frames: int
    candidates: float
    crossings: float
    first_stage_ms: float | None = None

    @property
    def second_stage_us_per_candidate(self) -> float | None:
        if self.first_stage_ms is None:
            return None
        return 1e3 * (self.median_ms - self.first_stage_ms) / max(self.candidates, 1.0)


def detector_latency(det, frames: list[Frame], *, repeats: int) -> DetectorLatency:
    """Time ``det.detect`` on each of ``frames`` with its depth (``repeats`` calls in all, spread evenly),
    and its first stage alone when it has later ones: frame by frame, one right after the other, so that
    both see the machine in the same state."""
    each = max(3, -(-repeats // len(frames)))
    two_stages = det.refiner is not None or det.depth_check is not None
    ours, first, kept, candidates = [], [], [], []
    for rgb, depth in frames:
        ours.append(
            _time_ms(lambda rgb=rgb, depth=depth: det.detect(rgb, depth=depth), repeats=each, warmup=2)
        )
        kept.append(len(det.detect(rgb, depth=depth)))
        with det.first_stage_only():
            if two_stages:
                first.append(
                    _time_ms(
                        lambda rgb=rgb, depth=depth: det.detect(rgb, depth=depth), repeats=each, warmup=2
                    )
                )
            candidates.append(len(det.detect(rgb, depth=depth)))
    ours = np.concatenate(ours)
    return DetectorLatency(
        median_ms=float(np.median(ours)),
        p90_ms=float(np.percentile(ours, 90)),
        frames=len(frames),
        candidates=float(np.mean(candidates)),
        crossings=float(np.mean(kept)),
        first_stage_ms=float(np.median(np.concatenate(first))) if two_stages else None,
    )


def _first_stage_words(det) -> str:
    """What the detector's first stage reads: the frame, or in the mirrored reading the frame and its mirror."""
    if det.reading == "mirrored":
        return "heatmap network on the frame and its mirror image, and peaks"
    return "heatmap network and peaks"


def _stages(lat: DetectorLatency, det) -> list[str]:
    """What the first stage and the later ones cost (nothing for one stage)."""
    if lat.first_stage_ms is None:
        return []
    return [
        f"perception:   of which the first stage ({_first_stage_words(det)}) {lat.first_stage_ms:.1f} ms "
        f"and the later ones (refining, verifying and checking in depth {lat.candidates:.0f} candidates a frame) "
        f"{lat.median_ms - lat.first_stage_ms:.1f} ms, {lat.second_stage_us_per_candidate:.0f} us a candidate"
    ]


def latency_frames() -> tuple[list[np.ndarray], str]:
    """The frames latency is measured on and what they are: :func:`rendered_frames`, or the drawn frame
    when the renderer cannot start here."""
    try:
        return rendered_frames(), f"{RENDERED_FRAMES} rendered paper-tunnel frames"
    except Exception as e:  # no EGL here: the drawn frame still times the detector
        return [drawn_frame()], f"the drawn frame (the renderer did not start: {type(e).__name__})"


def run(repeats: int = 100) -> list[str]:
    """Lines to print: latency of the shipped (or an untrained) detector and of its network in eager PyTorch."""
    import torch

    from rebar_data.perception.inference.detector import SHIPPED_MODEL, Detector, ray_grid
    from rebar_data.perception.inference.model_file import runtime_description
    from rebar_data.perception.networks.keypoint_net import KeypointNet, ModelConfig

    threads_before = torch.get_num_threads()
    torch.set_num_threads(THREADS)
    try:
        frames, described = latency_frames()
        load = os.getloadavg()
        lines = [
            f"perception: load average {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} (1 / 5 / 15 min) on "
            f"{os.cpu_count()} cores when the timing started"
        ]
        if SHIPPED_MODEL.exists():
            det, what = Detector.load(None, threads=THREADS), "shipped detector"
        else:
            from rebar_data.perception.networks.files import export_onnx

            tmp = Path(tempfile.mkdtemp())
            torch.manual_seed(0)
            export_onnx(KeypointNet(ModelConfig()), tmp / "untrained.onnx", {})
            det, what = (
                Detector.load(tmp / "untrained.onnx", threads=THREADS),
                "untrained detector (none shipped yet)",
            )
        lat = detector_latency(det, frames, repeats=repeats)
        med = lat.median_ms
        lines.append(
            f"perception: {what}, {runtime_description('auto')}, {det.reading} reading, {THREADS} threads, 640x480 "
            f"batch 1, end to end, over {described}: "
            f"median {med:.1f} ms, p90 {lat.p90_ms:.1f} ms a frame ({1e3 / med:.0f} Hz; "
            f"{lat.crossings:.0f} crossings found a frame; budget {BUDGET_MS:g} ms: "
            f"{'met' if med <= BUDGET_MS else 'MISSED'})"
        )
        lines += _stages(lat, det)
        if det.depth_check is not None:  # a camera without depth: the RGB stages alone, on the same frames
            rgb_frames = [(f[0], None) for f in frames]
            rgb_only = detector_latency(det, rgb_frames, repeats=repeats)
            stages = (
                "the RGB stages and the line check" if det.line_check is not None else "the RGB stages alone"
            )
            lines.append(
                f"perception:   without the depth image ({stages}): median {rgb_only.median_ms:.1f} ms, "
                f"p90 {rgb_only.p90_ms:.1f} ms ({rgb_only.median_ms / med:.2f}x the call with depth; budget "
                f"{BUDGET_MS:g} ms: {'met' if rgb_only.median_ms <= BUDGET_MS else 'MISSED'})"
            )
            if det.line_check is not None:  # what the line check costs there, on the same frames
                with_ms, without_ms = line_check_cost(det, [f[0] for f in frames], repeats=repeats)
                lines.append(
                    f"perception:   the line check: the RGB path {with_ms:.1f} ms with it, {without_ms:.1f} ms "
                    f"without (the RGB stages alone), timed in turn frame by frame ({with_ms / without_ms:.2f}x)"
                )
        if all(f[1] is not None for f in frames):  # what flattening what lies behind would cost
            flat_ms, kept_ms = flatten_cost(det, frames, repeats=repeats)
            lines.append(
                f"perception:   flattening what lies behind (--flatten-behind, off by default): the call with "
                f"depth {flat_ms:.1f} ms with it, {kept_ms:.1f} ms without, timed in turn frame by frame "
                f"({flat_ms / kept_ms:.2f}x)"
            )
        if det.reading == "mirrored":  # what the mirror image costs, same frames
            mirrored_ms, single_ms = reading_cost(det, [f[0] for f in frames], repeats=repeats)
            lines.append(
                f"perception:   the reading: the RGB path {mirrored_ms:.1f} ms mirrored, {single_ms:.1f} ms in the "
                f"single reading, timed in turn frame by frame ({mirrored_ms / single_ms:.2f}x)"
            )
        # a 1280x960 camera's frames, read at the trained focal length or as they come
        if det.focal_px is not None:
            resampled_ms, as_is_ms = focal_cost(det, [f[0] for f in frames], repeats=max(8, repeats // 4))
            lines.append(
                f"perception:   a 1280x960 frame (these enlarged twice, intrinsics with them): the RGB path "
                f"{resampled_ms:.1f} ms read at the trained focal length (resized to 640x480), {as_is_ms:.1f} ms "
                f"as it comes, timed in turn frame by frame ({as_is_ms / resampled_ms:.2f}x faster)"
            )
        if det.refiner is not None and det.refiner.has_int8_passes:  # what the int8 copy saves, same frames
            int8_ms, float_ms = int8_passes_cost(det, [f[0] for f in frames], repeats=repeats)
            passes = "every pass" if det.reading == "mirrored" else "the later passes"
            lines.append(
                f"perception:   the second stage's int8 copy ({passes}): the RGB path {int8_ms:.1f} ms, "
                f"{float_ms:.1f} ms with the float file instead, timed in turn frame by frame "
                f"({float_ms / int8_ms:.2f}x faster)"
            )
        if det.backend == "openvino":  # what the runtime saves, on the same frames
            ov_ms, ort_ms = runtime_cost(det, [f[0] for f in frames], repeats=repeats)
            lines.append(
                f"perception:   the runtime: the RGB path {ov_ms:.1f} ms with {runtime_description('auto')}, "
                f"{ort_ms:.1f} ms with ONNX Runtime in float32, timed in turn frame by frame "
                f"({ort_ms / ov_ms:.2f}x faster)"
            )
        if det.crossing_point is not None:  # the 3D crossing points as well, on the same frames
            each = max(3, -(-repeats // len(frames)))
            both = np.concatenate(
                [
                    _time_ms(
                        lambda f=f: det.detect(f[0], depth=f[1], point="crossing"), repeats=each, warmup=2
                    )
                    for f in frames
                ]
            )
            lines.append(
                f"perception:   with the crossing points (point='crossing'): median {np.median(both):.1f} ms "
                f"({np.median(both) / med:.2f}x the sight points' call)"
            )
        if len(frames) > 1:  # the worst case beside the typical one
            dense = detector_latency(det, [drawn_frame()], repeats=repeats)
            lines.append(
                f"perception: the drawn frame dense with bars ({dense.candidates:.0f} candidates, "
                f"{dense.crossings:.0f} kept"
                + (
                    "; its bars lie on the ground, which the depth check has not seen"
                    if det.depth_check is not None
                    else ""
                )
                + f"): median {dense.median_ms:.1f} ms, p90 {dense.p90_ms:.1f} ms"
            )
            lines += _stages(dense, det)
        rgb = frames[0][0]
        net = KeypointNet(ModelConfig()).eval()
        x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float()
        rays = torch.from_numpy(ray_grid(*FRAME_HW, (525.0, 525.0, 320.0, 240.0)))[None]  # output cells
        # the same network in the detector's runtime, with peak decoding (read twice in the mirrored reading)
        reference = lat.first_stage_ms or med
        ours = f"our first stage ({_first_stage_words(det)})"
        with torch.inference_mode():
            eager = _time_ms(lambda: net(x, rays), repeats=max(10, repeats // 5))
        lines.append(
            f"perception: same network in eager PyTorch (forward only): median {np.median(eager):.1f} ms "
            f"({np.median(eager) / reference:.1f}x {ours}, end to end)"
        )
        return lines
    finally:
        torch.set_num_threads(threads_before)
