"""The detector's crossing-point stage at inference: where each detection's 3D crossing point projects.

The detector finds the sight point, where the image shows the two bars cross (the dataset's u, v). The
3D crossing point, the midpoint of the two centerlines (inside the steel, DESIGN.md's crossing), lies
half the bars' combined diameter behind the top bar's centerline; under an oblique view it projects a
few pixels away. A small network reads the full-resolution patch around each detection with the
patch's viewing ray and gives that offset in pixels. Settings and why: :class:`~rebar_data.perception.
config.CrossingPointConfig`; training: :mod:`rebar_data.perception.training.crossing_point`.

This module needs no PyTorch for ONNX files, so the servo's detector loads without it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from rebar_data.errors import ConfigError
from rebar_data.perception.inference.refine import patches

# what a detection's pixel stands for: the sight point (where the image shows the bars cross, the
# dataset's labels) or the projected 3D crossing point (this stage's output)
POINTS = ("sight", "crossing")


def patch_rays(corners: np.ndarray, camera: tuple[float, float, float, float]) -> np.ndarray:
    """(N, 2) float32 viewing ray ((u - cx) / fx, (v - cy) / fy) of each patch centre (pixel corner)."""
    fx, fy, cx, cy = camera
    c = np.asarray(corners, np.float64).reshape(-1, 2)
    return np.c_[(c[:, 0] - cx) / fx, (c[:, 1] - cy) / fy].astype(np.float32)


class CrossingPoint:
    """A loaded crossing-point stage: ``offsets(image, uv, camera)`` gives, for each sight point ``uv``, the
    (N, 2) pixel offset to where its 3D crossing point projects."""

    def __init__(self, run: Callable[[np.ndarray, np.ndarray], np.ndarray], *, patch_px: int):
        self._run = run
        self.patch_px = patch_px

    @classmethod
    def load_onnx(cls, path: Path, *, threads: int, runtime: str = "onnxruntime") -> CrossingPoint:
        from rebar_data.perception.inference.runtime import onnx_session

        sess = onnx_session(path, threads, runtime)
        inputs = sess.get_inputs()
        size = inputs[0].shape[1]
        if len(inputs) != 2 or not isinstance(size, int):
            raise ConfigError(f"{path}: is not a crossing-point file (it takes no patches and rays)")
        names = [i.name for i in inputs]

        def run(x: np.ndarray, rays: np.ndarray) -> np.ndarray:
            return sess.run(None, {names[0]: x, names[1]: rays})[0]

        return cls(run, patch_px=size)

    def offsets(
        self, image: np.ndarray, uv: np.ndarray, camera: tuple[float, float, float, float]
    ) -> np.ndarray:
        """(N, 2) offsets from the (N, 2) sight points ``uv`` of the RGB ``image`` (pixels, COCO corner
        origin) to their projected 3D crossing points; ``camera`` is (fx, fy, cx, cy)."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        if not len(uv):
            return np.zeros((0, 2))
        x, corners = patches(image, uv, self.patch_px)
        return self._run(x, patch_rays(corners, camera)).astype(np.float64)

    def points(
        self, image: np.ndarray, uv: np.ndarray, camera: tuple[float, float, float, float]
    ) -> np.ndarray:
        """(N, 2) projected 3D crossing points of the sight points ``uv``."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        return uv + self.offsets(image, uv, camera)


def check_point(point: str) -> str:
    """``point`` if it is one of :data:`POINTS`, else ConfigError."""
    if point not in POINTS:
        raise ConfigError(f"point = {point!r} is not accepted; accepted: one of {', '.join(POINTS)}")
    return point
