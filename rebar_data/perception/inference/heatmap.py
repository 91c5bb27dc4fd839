"""The first stage's output grid: its stride, the rays of its cells, and crossings read from its heatmap.

Output cell (i, j) at stride 4 covers input pixels [4j, 4j + 4) x [4i, 4i + 4), so its centre is at
(4j + 2, 4i + 2) in COCO's corner origin.
"""

from __future__ import annotations

import cv2
import numpy as np

STRIDE = 4
INPUT_MULTIPLE = 16  # the encoder halves the size four times
OPERATING_THRESHOLD = 0.5  # the score ``detect`` returns from by default, and the metrics' operating point


def ray_grid(
    height: int, width: int, camera: tuple[float, float, float, float], *, stride: int = STRIDE
) -> np.ndarray:
    """(2, H / stride, W / stride) viewing rays ((u - cx) / fx, (v - cy) / fy) at the centres of the
    stride x stride cells of an H x W image (COCO corner origin: cell j's centre is at stride * (j + 0.5))."""
    fx, fy, cx, cy = camera
    u = (stride * (np.arange(-(-width // stride), dtype=np.float64) + 0.5) - cx) / fx
    v = (stride * (np.arange(-(-height // stride), dtype=np.float64) + 0.5) - cy) / fy
    return np.stack(np.broadcast_arrays(u[None, :], v[:, None])).astype(np.float32)


def decode(
    heat_logit: np.ndarray,
    offset: np.ndarray,
    *,
    threshold: float,
    max_detections: int = 1000,
) -> np.ndarray:
    """Crossings from one output: local maxima (3x3) of the heatmap with a score of at least ``threshold``.

    Peaks are found on the logits, which do not saturate the way float32 probabilities do near 1, so two
    neighbouring cells never tie and give one crossing twice.

    Args:
        heat_logit: (H, W) heatmap logits.
        offset: (2, H, W) offsets in cells.
        threshold: Lowest score (probability) kept, in (0, 1).
        max_detections: Most crossings returned, best first.

    Returns:
        (N, 3) u, v, score in input pixels (COCO corner origin), sorted by score, best first.
    """
    heat_logit = np.ascontiguousarray(heat_logit, np.float32)
    t = np.clip(threshold, 1e-7, 1 - 1e-7)
    floor = np.log(t / (1 - t))
    peak = (heat_logit >= cv2.dilate(heat_logit, np.ones((3, 3), np.uint8))) & (heat_logit >= floor)
    i, j = np.nonzero(peak)
    logit = heat_logit[i, j].astype(np.float64)
    order = np.argsort(-logit, kind="stable")[:max_detections]
    i, j, logit = i[order], j[order], logit[order]
    u = STRIDE * (j + 0.5 + offset[0, i, j])
    v = STRIDE * (i + 0.5 + offset[1, i, j])
    return np.c_[u, v, 1.0 / (1.0 + np.exp(-logit))]
