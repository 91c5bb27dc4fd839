"""A frame before the stages read it: resized to the trained focal length (:func:`focal_scale`), and on
request what lies far behind the front bars taken out of it (:func:`flatten_behind`, given depth)."""

from __future__ import annotations

import cv2
import numpy as np

from rebar_data.camera import Intrinsics

TOLERANCE = 0.15  # a frame whose focal length is within this share of the trained one is read as it comes


def focal_scale(trained_focal_px: float | None, camera: Intrinsics) -> float:
    """The factor that brings ``camera``'s focal length to ``trained_focal_px``; 1 when that is unknown or
    within :data:`TOLERANCE`."""
    if not trained_focal_px:
        return 1.0
    focal = 0.5 * (float(camera.fx) + float(camera.fy))
    if focal <= 0:
        return 1.0
    scale = float(trained_focal_px) / focal
    return 1.0 if abs(scale - 1.0) <= TOLERANCE else scale


def resample(image: np.ndarray, size: tuple[int, int], *, nearest: bool = False) -> np.ndarray:
    """``image`` resized to ``size`` (height, width): area averaging to shrink, bilinear to grow, the
    nearest pixel with ``nearest`` (depth)."""
    h, w = image.shape[:2]
    smooth = cv2.INTER_AREA if size[0] * size[1] < h * w else cv2.INTER_LINEAR
    return cv2.resize(image, (size[1], size[0]), interpolation=cv2.INTER_NEAREST if nearest else smooth)


GAP_M = 0.08  # farther than the nearest surface around by this much: behind (a lower mat lies 80-250 mm)
WINDOW_PX = 60  # the opening's square, full-resolution pixels (15 cells of 4 px)
CELL_PX = 4  # the resolution the nearest surface and the fill are worked out at
BLUR_CELLS = 4.0  # the fill's Gaussian sigma, in cells (16 px)


def front_depth(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) float32 metres: the depth of the nearest surface around each pixel (0 in ``depth_m`` = none),
    the opening over :data:`WINDOW_PX` squares at a quarter of the resolution; inf where none is measured."""
    d = np.asarray(depth_m, np.float32)
    h, w = d.shape
    hc, wc = -(-h // CELL_PX), -(-w // CELL_PX)
    padded = np.full((hc * CELL_PX, wc * CELL_PX), np.inf, np.float32)
    np.copyto(padded[:h, :w], d, where=d > 0)
    # each cell's nearest measurement
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


def behind_mask(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) bool: the measured pixels of ``depth_m`` more than ``GAP_M`` behind :func:`front_depth`."""
    d = np.asarray(depth_m, np.float32)
    return (d > 0) & (d > front_depth(d) + np.float32(GAP_M))


def flatten_behind(image: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """A copy of ``image`` (H, W, 3) uint8 whose pixels :func:`behind_mask` names take the blurred colour of
    such pixels around them; ``depth_m`` is registered to it."""
    behind = behind_mask(depth_m)
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
