"""The scale the detector reads an image at: its camera's focal length brought to the one it trained at.

Every frame the shipped detector trained on came from one focal length, 525 px (the Kinect v1 colour
camera; ``meta["focal_px"]``, the median over its training frames). A camera with another focal length
shows the same bar at the same distance larger or smaller in pixels: a 1280x960 camera with the same
field of view shows it twice as large. The first stage ranks crossings by how they look at the scale it
trained at, so ``Detector.detect`` resamples a frame whose focal length (the mean of fx and fy) differs
from the trained one by more than :data:`TOLERANCE` to that focal length, runs every stage there, and
returns positions in the caller's pixels. Without intrinsics the detector assumes the training camera's
field of view (``Detector.default_camera``), so a 1280-pixel-wide frame is read at 640. Training crops
each frame at the model's focal length alike (``Source.gain``; ``TrainingImages(focal_px=)``): `rebar adapt`
learns another camera's frames at the scale ``detect`` reads them.

Within 15% a frame is read as it comes: the first stage trained on crops scaled 0.7-1.4 (distances vary
as much), and a frame made smaller has fewer pixels to place a crossing with. The servo suites' Kinect
(57 degrees, fx 589.4: 12% longer than 525) shows it: resampled, the paper suite's worst IBVS visit ended
1.17 mm from its crossing, over the suite's 1 mm bar (0.97 mm as it comes), while on the cross-renderer
sets enlarged by the same 1.12 resampling kept PCK@2px the same and moved recall at precision 0.99 by
0.014-0.023 (below).

Measured on the shipped model, RGB only (`rebar detect`'s figures by script on the cross-renderer sets,
each frame resized by the factor first, its intrinsics with it; recall at precision 0.99 as the frame
came / resampled, crossval-planar and crossval-tunnel): x2 (a 1280x960 camera) 0.727 / 0.925 and 0.470 /
0.889, PCK@2px in the original pixels 0.841 / 0.958 and 0.826 / 0.939; x1.5 0.914 / 0.918 and 0.796 /
0.877; x1.12 (the servo suites' Kinect at 57 degrees, fx 589.4) 0.902 / 0.925 and 0.881 / 0.895; x0.75
0.827 / 0.910 and 0.782 / 0.891. At the sets' own scale 0.940 and 0.915: resampling twice costs a
little, reading at the wrong scale a lot.
"""

from __future__ import annotations

import numpy as np

# a frame whose focal length is within this share of the trained one is read as it comes (why: the module's text)
TOLERANCE = 0.15


def focal_scale(trained_focal_px: float | None, camera: tuple[float, float, float, float]) -> float:
    """The factor a frame taken with ``camera`` (fx, fy, cx, cy) is resized by so that its focal length is
    ``trained_focal_px``; 1 when that is unknown (a model file written before it was stored) or the two
    lie within :data:`TOLERANCE`."""
    if not trained_focal_px:
        return 1.0
    focal = 0.5 * (float(camera[0]) + float(camera[1]))
    if focal <= 0:
        return 1.0
    scale = float(trained_focal_px) / focal
    return 1.0 if abs(scale - 1.0) <= TOLERANCE else scale


def resampled_size(height: int, width: int, scale: float) -> tuple[int, int]:
    """(height, width) of a frame resized by ``scale``, at least one pixel each way."""
    return max(1, round(height * scale)), max(1, round(width * scale))


def resample(image: np.ndarray, size: tuple[int, int], *, nearest: bool = False) -> np.ndarray:
    """``image`` resized to ``size`` (height, width): area averaging when it shrinks, bilinear when it
    grows, the nearest pixel with ``nearest`` (a depth image, whose values must not blend across an
    edge). Corner-origin coordinates scale by exactly the ratio of the sizes."""
    import cv2  # here: the command line reads TOLERANCE without loading OpenCV

    h, w = image.shape[:2]
    smooth = cv2.INTER_AREA if size[0] * size[1] < h * w else cv2.INTER_LINEAR
    return cv2.resize(image, (size[1], size[0]), interpolation=cv2.INTER_NEAREST if nearest else smooth)


def scaled_camera(
    camera: tuple[float, float, float, float], sx: float, sy: float
) -> tuple[float, float, float, float]:
    """The intrinsics of a frame resized by ``sx`` across and ``sy`` down (COCO corner origin: the principal
    point scales with the pixels)."""
    fx, fy, cx, cy = camera
    return fx * sx, fy * sy, cx * sx, cy * sy
