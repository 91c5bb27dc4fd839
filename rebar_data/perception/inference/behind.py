"""What lies far behind the bars in front, taken out of the colour image before the stages read it.

Given the depth image registered to the colour one, ``detect`` (with ``Detector.flatten_behind``; `rebar
detect DATASET --flatten-behind`) replaces every pixel that lies more than :data:`GAP_M` behind the nearest
surface around it (the lower mat's bars, the ground and the bars' shadows on it) with the blurred colour of
such pixels nearby (:func:`flatten_behind`). The top mat's bars, and so its crossings, stay as they are;
what a patch shows around a crossing is then the crossing alone. The model's stages read the result; the
depth check reads the depth image as before.

The nearest surface (:func:`front_depth`) is the depth image's morphological opening (a minimum, then a
maximum, over :data:`WINDOW_PX` squares) at a quarter of the resolution: the bars in front fill each
window, a tilted or curved mat keeps its own depth (an opening returns a ramp as it is), and anything
narrower than the window that lies farther (a lower bar seen between the top ones, the ground between
them) is measured against the bars around it. Pixels without a measurement (0) are kept, and so is what a
window clipped by the frame's edge finds no bar in front of (a corner beyond the outermost bars).

Measured with the shipped model (2026-11-27, this project's 2-core machine; `rebar detect DATASET --split S
[--flatten-behind] --out p.parquet --metrics m.json`, the `-e` sets every split), AP@0.5 / PCK@2px /
recall at precision 0.99 given the dataset's depth image, as it comes -> flattened:

- paper-tunnel test: 0.979 / 0.953 / 0.993 -> 0.990 / 0.991 / 0.996 (median error 0.50 -> 0.32 px);
- crossval-planar: 0.979 / 0.964 / 0.987 -> 0.990 / 0.984 / 0.995;
- crossval-tunnel: 0.967 / 0.950 / 0.981 -> 0.990 / 0.990 / 0.997;
- cycles-train-planar-e: 0.966 / 0.934 / 0.980 -> 0.990 / 0.986 / 0.993;
- cycles-train-tunnel-e: 0.947 / 0.904 / 0.976 -> 0.990 / 0.979 / 0.989.

Why it is off by default:

- **Registration.** It needs the depth image registered to the colour one within about a pixel. With a
  Kinect v1's depth noise and disparity steps (:func:`~rebar_data.servo.camera.kinect_depth`) on
  paper-tunnel's test depth images it still scores 0.990 / 0.978 / 0.991 (0.978 / 0.953 / 0.985 as they
  come). With that depth 1 px to the side of the colour image, 0.990 / 0.974 / 0.987 (median error 0.69 px
  against 0.50 as they come); 2 px to the side, 0.989 / 0.934 / 0.986, median error 1.26 px (0.979 / 0.950
  / 0.981, 0.50 px as they come): the fill eats one side of each bar and the crossings move with it.
  Tried and not adopted: keeping 2 or 3 px around the bars in front (a halo the second stage misplaces;
  PCK@2px 0.970 / 0.956 registered, 0.953 / 0.947 shifted 2 px); moving the flattened region by the
  offset (within 3 px) that lands its edges on the colour image's edges (PCK@2px 0.975 registered, 0.956
  shifted 2 px, AP@0.5 0.957 there); and, with that offset, reading a frame found 2 px or more off as it
  comes. The offset named paper-tunnel's shift well (2 px: -2 in 65-67 of 120 frames, -1 in 18), but on
  the Cycles frames, registered exactly, it named 2-3 px in 5 of 48 (cycles-train-tunnel-e) and 6 of 24
  (crossval-planar); cycles-train-tunnel-e scored 0.963 / 0.939 / 0.975 so.
- **The servo.** `make eval`'s suites with it on (`Detector.flatten_behind` set; a suite's
  ``detector_flatten_behind``): paper IBVS / PBVS worst true lateral error 0.98 / 0.50 mm (0.97 / 0.24
  without; the bars 1.0 / 2.0 mm), paper-lower-mat 1.44 / 0.51 mm (1.80 / 1.51 without), random the same
  (its detector is not the network). The paper run's worst visit lies 1 px from the true crossing with and
  without it, and moved to 1.03 mm with a first version of the fill (blurred at full resolution) that
  scored the same on the datasets.

The windows and gap tried, on paper-tunnel test / crossval-planar PCK@2px: a plain minimum over 61 px (no
maximum after it) took the near side of a tilted mat for its front and removed the far side's bars (0.982
/ 0.924 with a 0.08 m gap; 0.932 on paper-tunnel with 0.05 m); openings of 60 px (shipped) 0.991 / 0.984
and of 124 px 0.981 / 0.955.
"""

from __future__ import annotations

import cv2
import numpy as np

GAP_M = 0.08  # farther than the nearest surface around by this much: behind (a lower mat lies 80-250 mm)
WINDOW_PX = 60  # the opening's square, full-resolution pixels (15 cells of 4 px)
CELL_PX = 4  # the resolution the nearest surface and the fill are worked out at
BLUR_CELLS = 4.0  # the fill's Gaussian sigma, in cells (16 px)


def front_depth(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) float32 metres: the depth of the nearest surface around each pixel of ``depth_m`` (metres, 0 =
    no measurement), as the module text says; inf where a window holds no measurement."""
    d = np.asarray(depth_m, np.float32)
    h, w = d.shape
    hc, wc = -(-h // CELL_PX), -(-w // CELL_PX)
    padded = np.full((hc * CELL_PX, wc * CELL_PX), np.inf, np.float32)
    np.copyto(padded[:h, :w], d, where=d > 0)
    # each cell's nearest measurement (a minimum over the cell's square, read at its corner; numpy's
    # reduction over the cells' axes gives the same 27 times as slowly)
    cells = cv2.erode(padded, np.ones((CELL_PX, CELL_PX), np.uint8), anchor=(0, 0))[::CELL_PX, ::CELL_PX]
    k = np.ones((WINDOW_PX // CELL_PX,) * 2, np.uint8)
    opened = cv2.dilate(
        cv2.erode(cells, k, borderType=cv2.BORDER_REPLICATE), k, borderType=cv2.BORDER_REPLICATE
    )
    finite = np.isfinite(opened)
    # cells with no measurement in reach take no part in the upsampling (inf would spread)
    filled = np.where(finite, opened, 0.0).astype(np.float32)
    up = cv2.resize(filled, (wc * CELL_PX, hc * CELL_PX), interpolation=cv2.INTER_LINEAR)[:h, :w]
    if not finite.all():
        reach = cv2.resize(
            finite.astype(np.uint8), (wc * CELL_PX, hc * CELL_PX), interpolation=cv2.INTER_NEAREST
        )
        up = np.where(reach[:h, :w] > 0, up, np.inf).astype(np.float32)
    return up


def behind_mask(depth_m: np.ndarray, *, gap_m: float = GAP_M) -> np.ndarray:
    """(H, W) bool: the measured pixels of ``depth_m`` lying more than ``gap_m`` behind :func:`front_depth`."""
    d = np.asarray(depth_m, np.float32)
    return (d > 0) & (d > front_depth(d) + np.float32(gap_m))


def flatten_behind(image: np.ndarray, depth_m: np.ndarray, *, gap_m: float = GAP_M) -> np.ndarray:
    """``image`` (H, W, 3) uint8 with the pixels :func:`behind_mask` names replaced by the blurred colour of
    those pixels around them (a normalised Gaussian at a quarter of the resolution); the others as they
    are. ``depth_m`` is registered to it, in metres (0 = no measurement). A new array; ``image`` is left."""
    behind = behind_mask(depth_m, gap_m=gap_m)
    out = image.copy()
    if not behind.any():
        return out
    h, w = behind.shape
    small = (max(1, w // CELL_PX), max(1, h // CELL_PX))
    mask = behind.view(np.uint8)
    masked = cv2.bitwise_and(image, image, mask=mask).astype(np.float32)
    weight = cv2.GaussianBlur(
        cv2.resize(mask.astype(np.float32), small, interpolation=cv2.INTER_AREA), (0, 0), BLUR_CELLS
    )
    colour = cv2.GaussianBlur(cv2.resize(masked, small, interpolation=cv2.INTER_AREA), (0, 0), BLUR_CELLS)
    fill = colour / np.maximum(weight, 1e-3)[..., None]
    fill = cv2.resize(np.clip(fill + 0.5, 0, 255).astype(np.uint8), (w, h), interpolation=cv2.INTER_LINEAR)
    cv2.copyTo(fill, mask, out)
    return out
