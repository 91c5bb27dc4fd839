"""The eye-in-hand RGB-D camera: a Kinect v1's intrinsics, its depth range and a robust depth reading.

The pinhole model (projection, back-projection, rays, conventions) is :class:`rebar_data.camera.Intrinsics`;
the depth image comes from the shared depth sensor models (:mod:`rebar_data.render.depth_sensor`).

Field of view: Kinect v1's nominal one is 57 x 43 degrees. With square pixels at 640x480 that is
``fx = fy = 320 / tan(28.5 deg) = 589.4`` px, which gives 57.0 x 44.3 degrees (the common calibration
``fx = 525`` gives 62.7 x 49.1). We keep square pixels and the 57 degree horizontal field.
"""

from __future__ import annotations

import numpy as np

from rebar_data.camera import Intrinsics

KINECT_FOV_X_DEG = 57.0
KINECT_WIDTH, KINECT_HEIGHT = 640, 480
KINECT_RANGE_M = (0.5, 4.5)  # the structured-light depth sensor's range (rebar_data.render.depth_sensor)


def kinect_intrinsics(fov_x_deg: float = KINECT_FOV_X_DEG) -> Intrinsics:
    """Kinect v1 colour camera with square pixels and the given horizontal field of view."""
    f = (KINECT_WIDTH / 2) / np.tan(np.radians(fov_x_deg) / 2)
    return Intrinsics(KINECT_WIDTH, KINECT_HEIGHT, f, f, KINECT_WIDTH / 2, KINECT_HEIGHT / 2)


def depth_at(
    depth_m: np.ndarray,
    uv: np.ndarray,
    *,
    window_px: int = 5,
    percentile: float = 50.0,
    front_band_m: float | None = None,
) -> float:
    """A robust depth reading around a pixel: a percentile of the valid depths in a square window.

    With ``front_band_m``, only the window's front surface counts: the depths within that band of its
    nearest tenth. A window on a bar whose sensor left holes (a structured-light shadow, a dropout) may hold
    more readings of what lies behind it (the lower mat, the ground) than of the bar; the median of all of
    them is then a depth behind the bar.

    Returns NaN when no pixel of the window has a measurement (or the pixel is outside the image).
    """
    h, w = depth_m.shape
    u, v = float(uv[0]), float(uv[1])
    if not (np.isfinite(u) and np.isfinite(v)):
        return float("nan")
    cu, cv = int(np.floor(u)), int(np.floor(v))
    r = window_px // 2
    u0, u1, v0, v1 = max(cu - r, 0), min(cu + r + 1, w), max(cv - r, 0), min(cv + r + 1, h)
    if u0 >= u1 or v0 >= v1:
        return float("nan")
    patch = depth_m[v0:v1, u0:u1]
    vals = patch[patch > 0]
    if vals.size == 0:
        return float("nan")
    if front_band_m is not None:
        vals = vals[vals <= np.percentile(vals, 10.0) + front_band_m]
    return float(np.percentile(vals, percentile))
