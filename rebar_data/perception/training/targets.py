"""Heatmap targets from keypoints, and keypoints from a predicted heatmap: the two must mirror each other.

Output cell (i, j) at stride 4 covers input pixels [4j, 4j + 4) x [4i, 4i + 4), so its centre is at
(4j + 2, 4i + 2) in COCO's corner origin. A crossing at (u, v) lies in cell (floor(v / 4), floor(u / 4));
that cell's heatmap target is 1, its neighbours get a Gaussian of the cell distance (CenterNet's
penalty-reduced negatives), and the 3x3 cells around it learn the offset from their own centre to the
crossing, so decoding still lands on the crossing when the peak falls in a neighbouring cell."""

from __future__ import annotations

import numpy as np

from rebar_data.perception.inference.detector import STRIDE

OFFSET_RADIUS = 1  # offsets are learned in the (2r+1)^2 cells around each crossing
IGNORE_RADIUS = 2  # cells around an ignored point left out of the heatmap loss


def encode_targets(
    positives: np.ndarray, ignore: np.ndarray, out_h: int, out_w: int, *, sigma_cells: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Targets for one crop of ``out_h`` x ``out_w`` cells: heat (H, W) in [0, 1], exactly 1 at each
    crossing's cell; heat_weight (H, W), 0 around the ``ignore`` points; offset (2, H, W) in cells;
    offset_weight (H, W), 1 where an offset is learned. ``positives`` and ``ignore`` are in input pixels."""
    heat = np.zeros((out_h, out_w), np.float32)
    heat_weight = np.ones((out_h, out_w), np.float32)
    offset = np.zeros((2, out_h, out_w), np.float32)
    offset_weight = np.zeros((out_h, out_w), np.float32)
    best_d2 = np.full((out_h, out_w), np.inf, np.float32)
    r = int(np.ceil(3 * sigma_cells))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    blob = np.exp(-(xx**2 + yy**2) / (2 * sigma_cells**2)).astype(np.float32)
    for u, v in np.asarray(ignore, float).reshape(-1, 2):
        j, i = int(np.floor(u / STRIDE)), int(np.floor(v / STRIDE))
        i0, i1 = max(i - IGNORE_RADIUS, 0), min(i + IGNORE_RADIUS + 1, out_h)
        j0, j1 = max(j - IGNORE_RADIUS, 0), min(j + IGNORE_RADIUS + 1, out_w)
        heat_weight[i0:i1, j0:j1] = 0.0
    for u, v in np.asarray(positives, float).reshape(-1, 2):
        gx, gy = u / STRIDE - 0.5, v / STRIDE - 0.5  # position in cell-centre units
        j, i = int(np.floor(u / STRIDE)), int(np.floor(v / STRIDE))
        if not (0 <= i < out_h and 0 <= j < out_w):
            continue
        i0, i1, j0, j1 = max(i - r, 0), min(i + r + 1, out_h), max(j - r, 0), min(j + r + 1, out_w)
        b = blob[i0 - i + r : i1 - i + r, j0 - j + r : j1 - j + r]
        np.maximum(heat[i0:i1, j0:j1], b, out=heat[i0:i1, j0:j1])
        for di in range(-OFFSET_RADIUS, OFFSET_RADIUS + 1):
            for dj in range(-OFFSET_RADIUS, OFFSET_RADIUS + 1):
                ci, cj = i + di, j + dj
                if not (0 <= ci < out_h and 0 <= cj < out_w):
                    continue
                dx, dy = gx - cj, gy - ci
                d2 = dx * dx + dy * dy
                if d2 < best_d2[ci, cj]:  # a cell between two crossings points at the nearer one
                    best_d2[ci, cj] = d2
                    offset[:, ci, cj] = dx, dy
                    offset_weight[ci, cj] = 1.0
    heat_weight[heat >= 1.0] = 1.0  # a crossing next to an ignored one is still a positive
    return heat, heat_weight, offset, offset_weight
