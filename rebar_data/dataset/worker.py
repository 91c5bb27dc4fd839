"""Renders and labels the frames of one trajectory; one long-lived renderer per worker process.

A worker writes its images (and the exact and the sensor's depth maps, and instance maps) into the
staging folder and returns the
labels and per-frame parameters to the process that assembles the tables, so the tables do not
depend on which worker did what.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rebar_data.dataset import layout
from rebar_data.dataset.layout import INSTANCE_OFFSET
from rebar_data.dataset.plan import PlannedImage, depth_sensor_seed
from rebar_data.geometry.build import RebarMesh, build_rebar_mesh
from rebar_data.labels.keypoints import CrossingParts, FrameLabels, LabelRule, label_frame
from rebar_data.pipeline import PipelineConfig
from rebar_data.render.depth_sensor import depth_mm, sense_depth
from rebar_data.scene.cameras import intrinsics_from_config
from rebar_data.scene.sample import SceneSample, sample_depth_sensor, sample_sensor
from rebar_data.timing import StageTimer
from rebar_data.workers import renderer_process


@dataclass(frozen=True)
class FrameRecord:
    image_id: str
    labels: FrameLabels
    sensor: dict
    image_sha256: str


class FrameWorker:
    """Owns one renderer and the mesh; renders a trajectory's frames into ``staging``."""

    def __init__(self, cfg: PipelineConfig, staging: Path, rm: RebarMesh | None = None):
        from rebar_data.render.engines import renderer_class

        self.cfg = cfg
        self.staging = Path(staging)
        self.rm = rm if rm is not None else build_rebar_mesh(cfg.mesh_config())
        self.parts = CrossingParts.of(self.rm)
        self.intrinsics = intrinsics_from_config(cfg.camera)
        self.rule = LabelRule(**cfg.labels.model_dump())
        self.renderer = renderer_class(cfg.render)(self.intrinsics, cfg.render)
        self.renderer.set_mesh(self.rm)
        # seconds per stage of a frame: render, depth_sensor, labels, png, write (for the bench)
        self.timer = StageTimer()

    def run(self, scene: SceneSample, samples: list[PlannedImage]) -> list[FrameRecord]:
        with self.timer("scene"):
            self.renderer.set_scene(scene)
        return [self._one(s) for s in samples]

    def _one(self, s: PlannedImage) -> FrameRecord:
        import hashlib

        timer = self.timer
        rng = np.random.default_rng(s.seed)
        sensor = sample_sensor(self.cfg.scene, rng)
        with timer("render"):
            frame = self.renderer.render(s.world_from_camera, sensor, rng)
        sensed, depth_sensor = None, None
        if self.cfg.dataset.store_depth:
            with timer("depth_sensor"):
                depth_rng = np.random.default_rng(depth_sensor_seed(s.seed))
                depth_sensor = sample_depth_sensor(self.cfg.scene, depth_rng)
                sensed = sense_depth(frame.depth_m, depth_sensor, depth_rng, fx=self.intrinsics.fx)
        with timer("labels"):
            labels = label_frame(
                self.rm, self.parts, s.world_from_camera, self.intrinsics, self.renderer.cast_rays, self.rule
            )
        files = []
        with timer("png"):
            png = _encode(cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
            files.append((layout.image_path(s.split, s.image_id), png))
            if self.cfg.dataset.store_depth:
                files.append((layout.depth_path(s.split, s.image_id), _encode(depth_mm(frame.depth_m))))
                files.append((layout.sensor_depth_path(s.split, s.image_id), _encode(depth_mm(sensed))))
            if self.cfg.dataset.store_instances:
                inst = (frame.instance + INSTANCE_OFFSET).astype(np.uint16)
                files.append((layout.instance_path(s.split, s.image_id), _encode(inst)))
        with timer("write"):
            for path, data in files:
                _write(self.staging / path, data)
        record = sensor.record() | (depth_sensor.record() if depth_sensor is not None else {})
        return FrameRecord(s.image_id, labels, record, hashlib.sha256(png).hexdigest())

    def close(self) -> None:
        self.renderer.close()


# zlib's run-length strategy behind the Paeth filter: measured on paper-tunnel frames, 14 ms and 736 KiB a
# 640x640 RGB frame against 30 ms and 777 KiB with OpenCV's defaults at level 3 (the sensor noise makes
# longer matches rare, so the default strategy spends its time finding none); depth 5 ms, instances 2 ms.
PNG_PARAMS = [
    cv2.IMWRITE_PNG_COMPRESSION,
    3,
    cv2.IMWRITE_PNG_STRATEGY,
    cv2.IMWRITE_PNG_STRATEGY_RLE,
    cv2.IMWRITE_PNG_FILTER,
    cv2.IMWRITE_PNG_FILTER_PAETH,
]


def _encode(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img, PNG_PARAMS)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def _write(path: Path, data: bytes) -> None:
    """Write via a temporary name and rename, so a killed build never leaves a truncated file (and a
    failed write, such as on a full disk, no temporary one)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(data)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


# --- process-pool plumbing: one FrameWorker per process -------------------------------------------

_WORKER: FrameWorker | None = None


def init_process(cfg: PipelineConfig, staging: Path, rm: RebarMesh | None) -> None:
    """Set up a pool worker: its renderer, and Ctrl-C ignored (the build's process ends the workers)."""
    global _WORKER
    renderer_process()
    _WORKER = FrameWorker(cfg, staging, rm)


def stage_seconds_in_process() -> dict[str, dict[str, tuple[float, int]]]:
    """This process's worker's stage totals: the frame's (``frame``) and its renderer's (``render``)."""
    assert _WORKER is not None, "init_process was not called in this worker"
    return {"frame": _WORKER.timer.totals(), "render": _WORKER.renderer.timer.totals()}


def run_in_process(task: tuple[str, SceneSample, list[PlannedImage]]) -> tuple[str, list[FrameRecord]]:
    trajectory_id, scene, samples = task
    assert _WORKER is not None, "init_process was not called in this worker"
    return trajectory_id, _WORKER.run(scene, samples)
