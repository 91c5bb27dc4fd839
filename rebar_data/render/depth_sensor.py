"""What an RGB-D camera's depth sensor reports for an exact depth image: the depth sensor models.

Every model takes exact camera-frame z (metres, 0 = nothing hit) on the colour camera's pixel grid and
returns the sensor's z on the same grid, 0 where the sensor has no measurement. The depth camera is placed
at the colour camera; the residual offset between the two is a separate effect (:func:`misregister`).

Models (``DepthSensorSample.model``):

- ``exact``: the ray-cast z.
- ``structured_light``, Kinect v1-like. A projector at ``baseline_m`` = 75 mm along the IR camera's +x, the
  IR camera's focal length 580 px and disparity in 1/8 px steps (Khoshelham and Elberink, "Accuracy and
  resolution of Kinect depth data", Sensors 12(2), 2012); axial noise sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2
  m (Nguyen, Izadi and Lovell, 3DIMPVT 2012), scaled per frame; a correlation window of about 9 x 9 px
  (Konolige and Mihelich, "Technical description of Kinect calibration", ros.org kinect_calibration); range
  0.5-4.5 m. Surface points the projector cannot light (the shadow beside a foreground edge, on the side
  facing away from the projector, as wide as the disparity jump ``f b (1/z_near - 1/z_far)``) have no
  measurement (the projector's field is wider than the camera's, so the image's margin is lit); structures
  narrower than the window are lost to the surface behind them (the window's
  pattern is mostly the background's); smooth surfaces are averaged over the window.
- ``active_stereo``, RealSense D4xx-like (D435): a 50 mm baseline to the right imager, 447 px focal length
  at 848x480 (the datasheet's 87 degree field of view; Intel RealSense D400 series datasheet). Depth is in
  the left imager's frame, so points the right imager cannot see (a band beside every foreground edge on
  the left, and the image's left margin) have none. Disparity noise of 0.05-0.1 px RMS (Grunnet-Jepsen et
  al., "Tuning depth cameras for best performance", Intel white paper: RMS error = z^2 subpixel / (f b),
  subpixel about 0.08 px); the nearest measured z is ``f b / 126`` px of disparity search range (the same
  paper's Min-Z); the far limit is the datasheet's 10 m. Bars narrower than the matching window leave holes
  (the left-right check fails there). Intel does not publish the D4 ASIC's window size: 5-7 px is our
  assumption, and a config setting.
- ``time_of_flight``, Kinect v2 / Azure Kinect-like: no baseline, so no shadow band; pixels on a depth edge
  mix the foreground's and the background's returns into a flying pixel between the two (Sarbolandi,
  Lefloch and Kolb, "Kinect range sensing: structured-light versus time-of-flight Kinect", CVIU 139,
  2015); axial noise of 1-2 mm at 1 m growing by 1 mm a metre (Azure Kinect DK hardware specification:
  random error sigma <= 17 mm); range 0.5-4.5 m (Kinect v2 specification).

How such models are built elsewhere, read for this one: the ICL-NUIM benchmark's Kinect noise (Handa et
al., ICRA 2014: disparity noise and quantisation), simkinect, Landau, Choo and Beling's Kinect simulator
(IEEE Trans. Cybernetics 46(8), 2016: a projector shadow found by ray test) and BlenderProc's depth
postprocessing (Gaussian noise and dropout for the Azure Kinect, stereo matching). Here the shadow band
comes from an occlusion test along the baseline (the order of disparity-shifted columns in each row),
not from a dilation.
"""

from __future__ import annotations

import cv2
import numpy as np

from rebar_data.scene.config import DEPTH_MODELS
from rebar_data.scene.sample import DepthSensorSample

# a window whose disparities differ by more than this from a pixel's has an edge in it (pixels)
WINDOW_EDGE_PX = 0.5


def kinect_sigma_m(z_m: np.ndarray) -> np.ndarray:
    """Kinect v1 axial noise sigma (metres) at z: ``0.0012 + 0.0019 (z - 0.4)^2`` (Nguyen et al., 2012)."""
    return 0.0012 + 0.0019 * (np.asarray(z_m) - 0.4) ** 2


def unseen_from_offset_view(
    z_m: np.ndarray, fx: float, baseline_m: float, *, image_margin: bool = True
) -> np.ndarray:
    """Pixels a second view ``baseline_m`` along the camera's +x (-x when negative) cannot see.

    A pixel at column u and depth z lands at ``u - fx b / z`` in the second view. It is hidden there when
    a pixel to its right in the same row (left, for a view at -x) lands at or beyond it: the two rays cross
    before reaching it, and the nearer point wins. With ``image_margin``, points landing outside the
    second view's image (a second camera of the same field of view) are also unseen; a projector's wider
    field lights them. Nothing-hit pixels (z = 0) hide nothing.
    """
    z = np.asarray(z_m, np.float64)
    flip = baseline_m < 0
    if flip:
        z = z[:, ::-1]
    w = z.shape[1]
    hit = z > 0
    disparity = np.zeros_like(z)
    np.divide(fx * abs(baseline_m), z, out=disparity, where=hit)
    landed = np.arange(w, dtype=np.float64) + 0.5 - disparity
    first_right = np.full_like(landed, np.inf)
    first_right[:, :-1] = np.minimum.accumulate(landed[:, ::-1], axis=1)[:, ::-1][:, 1:]
    unseen = hit & ((landed >= first_right) | ((landed < 0.0) & image_margin))
    return unseen[:, ::-1] if flip else unseen


def _window(disparity: np.ndarray, window_px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The correlation window's effect on a disparity image (0 = none): (smoothed, lost, behind).

    ``lost``: pixels of a structure no window-sized square fits in (a morphological opening removes it);
    ``behind``: what the opening leaves there (the surface behind, 0 for nothing); ``smoothed``: the window
    mean where the window holds one smooth surface, the input elsewhere.
    """
    kernel = np.ones((window_px, window_px), np.uint8)
    low = cv2.erode(disparity, kernel, borderType=cv2.BORDER_REPLICATE)
    behind = cv2.dilate(low, kernel, borderType=cv2.BORDER_REPLICATE)
    high = cv2.dilate(disparity, kernel, borderType=cv2.BORDER_REPLICATE)
    lost = (disparity - behind) > WINDOW_EDGE_PX
    smooth = ((high - low) < WINDOW_EDGE_PX) & (low > 0)
    mean = cv2.blur(disparity, (window_px, window_px), borderType=cv2.BORDER_REPLICATE)
    return np.where(smooth, mean, disparity), lost, behind


def _disparity(z: np.ndarray, fb: float) -> np.ndarray:
    out = np.zeros(z.shape, np.float32)
    np.divide(np.float32(fb), z, out=out, where=z > 0)
    return out


def _in_range(z: np.ndarray, near_m: float, far_m: float) -> np.ndarray:
    return np.where((z >= near_m) & (z <= far_m), z, 0.0).astype(np.float32)


def structured_light(
    z_m: np.ndarray, s: DepthSensorSample, rng: np.random.Generator, *, fx: float
) -> np.ndarray:
    """Kinect v1-like depth: projector shadow, correlation window, axial noise, 1/8 px disparity steps."""
    z = np.asarray(z_m, np.float32)
    fb = fx * s.baseline_m
    d = _disparity(z, fb)
    d[unseen_from_offset_view(z, fx, s.baseline_m, image_margin=False)] = 0.0
    d, lost, behind = _window(d, s.window_px)
    d = np.where(lost, behind, d)
    out = _disparity(d, fb)  # back to z on the frame's pixel grid
    valid = out > 0
    zv = out[valid]
    zv = zv + rng.standard_normal(zv.shape, dtype=np.float32) * (s.noise * kinect_sigma_m(zv)).astype(
        np.float32
    )
    sensor_fb = s.focal_px * s.baseline_m
    step = s.disparity_step_px
    ds = np.round(sensor_fb / np.maximum(zv, 1e-3) / step) * step
    out[valid] = np.where(ds > 0, sensor_fb / np.maximum(ds, step), 0.0)
    return _in_range(out, s.near_m, s.far_m)


def active_stereo(
    z_m: np.ndarray, s: DepthSensorSample, rng: np.random.Generator, *, fx: float
) -> np.ndarray:
    """D4xx-like depth: right-imager occlusion band, holes for sub-window structures, subpixel noise."""
    z = np.asarray(z_m, np.float32)
    fb = fx * s.baseline_m
    d = _disparity(z, fb)
    d[unseen_from_offset_view(z, fx, s.baseline_m)] = 0.0
    d, lost, _ = _window(d, s.window_px)
    d[lost] = 0.0
    out = _disparity(d, fb)
    valid = out > 0
    sensor_fb = s.focal_px * s.baseline_m
    ds = sensor_fb / out[valid] + rng.standard_normal(int(valid.sum()), dtype=np.float32) * np.float32(
        s.noise
    )
    out[valid] = np.where(ds > 0, sensor_fb / np.maximum(ds, 1e-6), 0.0)
    return _in_range(out, s.near_m, s.far_m)


def time_of_flight(z_m: np.ndarray, s: DepthSensorSample, rng: np.random.Generator) -> np.ndarray:
    """ToF-like depth: flying pixels between the two sides of every depth edge, axial noise, range."""
    z = np.asarray(z_m, np.float32)
    hit = z > 0
    kernel = np.ones((3, 3), np.uint8)
    near = cv2.erode(np.where(hit, z, np.float32(np.inf)), kernel, borderType=cv2.BORDER_REPLICATE)
    near = np.where(np.isfinite(near), near, z)
    far = cv2.dilate(z, kernel, borderType=cv2.BORDER_REPLICATE)
    edge = hit & ((far - near) > s.edge_jump_m)
    mix = rng.random(z.shape, dtype=np.float32)
    flying = edge & (rng.random(z.shape, dtype=np.float32) < s.flying_pixel_probability)
    out = np.where(flying, near + mix * (far - near), z)
    sigma = np.float32(s.noise) + np.float32(s.noise_per_m) * out
    out = np.where(hit, out + rng.standard_normal(z.shape, dtype=np.float32) * sigma, 0.0)
    return _in_range(out, s.near_m, s.far_m)


def misregister(depth_m: np.ndarray, shift_x_px: float, shift_y_px: float) -> np.ndarray:
    """The depth image moved by (x, y) pixels against the colour image, resampled to the nearest pixel
    (depth is never interpolated across an edge), so it moves by the rounded offset; 0 where uncovered."""
    dx, dy = int(np.rint(shift_x_px)), int(np.rint(shift_y_px))
    if dx == 0 and dy == 0:
        return depth_m
    h, w = depth_m.shape
    out = np.zeros_like(depth_m)
    if abs(dx) >= w or abs(dy) >= h:
        return out
    out[max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)] = depth_m[
        max(-dy, 0) : h + min(-dy, 0), max(-dx, 0) : w + min(-dx, 0)
    ]
    return out


def sense_depth(z_m: np.ndarray, s: DepthSensorSample, rng: np.random.Generator, *, fx: float) -> np.ndarray:
    """The depth sensor ``s``'s image (float32 metres, 0 = no measurement) of exact z ``z_m`` (0 = nothing),
    misregistration included; ``fx`` is the frame's focal length in pixels, noise comes from ``rng``."""
    if s.model == "exact":
        out = np.asarray(z_m, np.float32).copy()
    elif s.model == "structured_light":
        out = structured_light(z_m, s, rng, fx=fx)
    elif s.model == "active_stereo":
        out = active_stereo(z_m, s, rng, fx=fx)
    elif s.model == "time_of_flight":
        out = time_of_flight(z_m, s, rng)
    else:
        raise ValueError(f"depth sensor model {s.model!r} is unknown; accepted: {', '.join(DEPTH_MODELS)}")
    return misregister(out, s.shift_x_px, s.shift_y_px)


def depth_mm(depth_m: np.ndarray) -> np.ndarray:
    """uint16 millimetres (0 = no measurement) of a metric depth image, as the dataset stores depth."""
    return np.clip(np.round(np.asarray(depth_m) * 1000.0), 0, 65535).astype(np.uint16)  # in the input's dtype
