"""Crossing detectors for the servo loop: the protocol, a ground-truth detector, faults, and the shipped model.

Anything with ``detect(rgb, *, depth) -> (N, 3)`` rows ``(u, v, score)`` in pixels and a ``dropped`` flag
(see :class:`Detector`) drops into the loop. The shipped model is :class:`rebar_data.perception.Detector`;
:class:`GroundTruthDetector` projects the crossings that are really visible with the exact camera pose
(for tests and for separating control from perception errors), and :class:`FaultyDetector` wraps either
one with dropped frames, pixel noise and spurious detections.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from rebar_data.camera import Intrinsics
from rebar_data.geometry.build import RebarMesh

if TYPE_CHECKING:
    from rebar_data.labels.keypoints import CastRays


class ServoDetector(Protocol):
    """What the loop calls. ``dropped`` says whether the last :meth:`detect` lost its frame to a fault (its
    step rows count it); a detector that never drops one declares ``dropped = False``."""

    dropped: bool

    def detect(self, rgb: np.ndarray, *, depth: np.ndarray | None = None) -> np.ndarray:
        """Detections (N, 3): u, v (pixels, COCO corner origin) and a score in [0, 1]; ``depth`` is the
        frame's metric depth (H, W), 0 = none, for a detector that checks its detections in depth."""
        ...


class GroundTruthDetector:
    """Projects every crossing visible from the true camera pose (visibility by the dataset's ray test).

    It reports the crossing's own point (the midpoint of the two centerlines), the target a tying tool
    needs, not the dataset's label (the sight point, where the image shows the bars crossing): the two
    differ by a bar radius times the sine of the view angle (about 1 mm with the random suite's tilted
    cameras), which is an error of a detector of that label, not of the loop this detector measures.

    It ignores the image: ``pose_fn`` returns the simulator's true ``world_from_camera`` at the moment
    of the frame, and ``cast_rays`` is the frame source's ray cast (so what hides a crossing in the
    frame hides it here too). A crossing counts when the dataset's label rule gives it visibility 2 (the first
    surface along the ray from the camera is one of its own bars, near the crossing) and it lies at
    least ``margin_px`` inside the image.
    """

    dropped = False

    def __init__(
        self,
        rm: RebarMesh,
        camera: Intrinsics,
        cast_rays: CastRays,
        pose_fn: Callable[[], np.ndarray],
        *,
        margin_px: float = 4.0,
    ):
        from rebar_data.labels.keypoints import CrossingParts

        self._rm, self._camera, self._cast_rays, self._pose_fn = rm, camera, cast_rays, pose_fn
        self._parts = CrossingParts.of(rm)
        self._margin = margin_px
        self.last_crossing_ids = np.zeros(0, np.int64)

    def detect(self, rgb: np.ndarray, *, depth: np.ndarray | None = None) -> np.ndarray:
        from rebar_data.labels.keypoints import label_frame

        world_from_camera = self._pose_fn()
        labels = label_frame(self._rm, self._parts, world_from_camera, self._camera, self._cast_rays)
        T = np.linalg.inv(world_from_camera)
        uv = self._camera.project(self._rm.crossings.point @ T[:3, :3].T + T[:3, 3])
        c, m = self._camera, self._margin
        with np.errstate(invalid="ignore"):
            keep = (labels.visibility == 2) & (uv[:, 0] >= m) & (uv[:, 0] < c.width - m)
            keep &= (uv[:, 1] >= m) & (uv[:, 1] < c.height - m)
        idx = np.nonzero(keep)[0]
        self.last_crossing_ids = idx
        return np.stack([uv[idx, 0], uv[idx, 1], np.ones(len(idx))], axis=1)


@dataclass(frozen=True)
class Faults:
    """Detector faults: a share of frames with no detections, Gaussian pixel noise (per axis), spurious hits."""

    drop_fraction: float = 0.0
    pixel_noise_px: float = 0.0
    spurious_per_frame: float = 0.0

    @property
    def active(self) -> bool:
        return self.drop_fraction > 0 or self.pixel_noise_px > 0 or self.spurious_per_frame > 0


class FaultyDetector:
    """Wraps a detector with faults drawn from its own generator.

    A dropped frame returns no detections; every detection moves by N(0, ``pixel_noise_px``) on each
    axis; ``spurious_per_frame`` is the expected number of false detections per frame (Poisson), each at
    a uniformly random pixel with a random score in [0.5, 1].
    """

    def __init__(
        self, inner: ServoDetector, faults: Faults, rng: np.random.Generator, *, width: int, height: int
    ):
        self.inner, self.faults, self._rng = inner, faults, rng
        self._size = (width, height)
        self.dropped = False

    def detect(self, rgb: np.ndarray, *, depth: np.ndarray | None = None) -> np.ndarray:
        f, rng = self.faults, self._rng
        det = np.asarray(self.inner.detect(rgb, depth=depth), float).reshape(-1, 3).copy()
        self.dropped = bool(rng.random() < f.drop_fraction)
        if self.dropped:
            return np.zeros((0, 3))
        if f.pixel_noise_px > 0:
            det[:, :2] += rng.normal(0.0, f.pixel_noise_px, (len(det), 2))
        n_spurious = rng.poisson(f.spurious_per_frame) if f.spurious_per_frame > 0 else 0
        if n_spurious:
            w, h = self._size
            fake = np.stack(
                [
                    rng.uniform(0, w, n_spurious),
                    rng.uniform(0, h, n_spurious),
                    rng.uniform(0.5, 1.0, n_spurious),
                ],
                axis=1,
            )
            det = np.vstack([det, fake])
        return det


class _WithCamera:
    """The shipped detector, which takes the camera's intrinsics, bound to this camera (None: its default
    camera): ``detect(rgb, depth=...)`` as the loop calls it."""

    dropped = False

    def __init__(self, inner, camera: Intrinsics | None):
        self.inner = inner
        self._camera = camera

    def detect(self, rgb: np.ndarray, *, depth: np.ndarray | None = None) -> np.ndarray:
        return self.inner.detect(rgb, camera=self._camera, depth=depth)


def load_shipped_detector(
    path: str | Path | None = None,
    camera: Intrinsics | None = None,
    *,
    runtime: str = "auto",
    reading: str = "single",
    flatten_behind: bool = False,
) -> ServoDetector:
    """A suite's ``detector: shipped``: :meth:`rebar_data.perception.Detector.load` of ``path`` (None: the
    shipped model) with the suite's ``runtime``, ``reading`` and ``flatten_behind``, bound to ``camera``'s
    intrinsics (None: the detector's default camera)."""
    from rebar_data.perception import Detector as ShippedDetector

    det = ShippedDetector.load(path, runtime=runtime, reading=reading, flatten_behind=flatten_behind)
    return _WithCamera(det, camera)
