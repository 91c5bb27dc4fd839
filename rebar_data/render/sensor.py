"""The camera model applied to a rendered linear image: optics, exposure, noise, tone curve, JPEG.

Order, as in a real camera: defocus and motion blur (optics), vignetting, exposure gain (auto-exposure on
the log-average luminance, then the frame's ``exposure_ev``), shot and read noise (sensor), a filmic tone
curve with the sRGB transfer function (image processor), JPEG compression. Every random number comes from
the generator passed in.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from rebar_data.scene.sample import SensorSample

MID_GREY = 0.18
_LUT_SCALE = 4096.0  # tone LUT entries per unit of linear exposure
_LUT_SIZE = 65536


@lru_cache(maxsize=1)
def _tone_lut() -> np.ndarray:
    """uint8 sRGB output for linear exposure ``i / _LUT_SCALE`` (ACES filmic fit, then sRGB)."""
    x = np.arange(_LUT_SIZE, dtype=np.float64) / _LUT_SCALE
    y = (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)
    y = np.clip(y, 0.0, 1.0)
    s = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1.0 / 2.4) - 0.055)
    return np.clip(np.round(s * 255.0), 0, 255).astype(np.uint8)


@lru_cache(maxsize=4)
def _radius2(height: int, width: int, cx: float, cy: float) -> np.ndarray:
    """Squared distance from the principal point, 1 at the farthest image corner."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    r2 = (u + 0.5 - cx) ** 2 + (v + 0.5 - cy) ** 2
    return (r2 / r2.max()).astype(np.float32)


def disk_kernel(radius_px: float) -> np.ndarray:
    """Anti-aliased disk (defocus point spread), normalised to sum 1."""
    half = int(np.ceil(radius_px + 1))
    sub = 4
    g = (np.arange(-half * sub, (half + 1) * sub) + 0.5) / sub - 0.5
    yy, xx = np.meshgrid(g, g, indexing="ij")
    inside = (xx**2 + yy**2 <= radius_px**2).astype(np.float32)
    k = inside.reshape(2 * half + 1, sub, 2 * half + 1, sub).mean(axis=(1, 3))
    return k / k.sum()


def line_kernel(length_px: float, angle_deg: float) -> np.ndarray:
    """Motion blur along a line of ``length_px`` at ``angle_deg`` (image x towards y), sum 1."""
    half = int(np.ceil(length_px / 2 + 1))
    k = np.zeros((2 * half + 1, 2 * half + 1), np.float32)
    t = np.linspace(-length_px / 2, length_px / 2, max(int(length_px * 8), 2))
    a = np.radians(angle_deg)
    xs, ys = half + t * np.cos(a), half + t * np.sin(a)
    x0, y0 = np.floor(xs).astype(int), np.floor(ys).astype(int)
    fx, fy = xs - x0, ys - y0
    for dx, dy, w in (
        (0, 0, (1 - fx) * (1 - fy)),
        (1, 0, fx * (1 - fy)),
        (0, 1, (1 - fx) * fy),
        (1, 1, fx * fy),
    ):
        np.add.at(k, (y0 + dy, x0 + dx), w.astype(np.float32))
    return k / k.sum()


def apply_sensor(
    linear: np.ndarray,
    sensor: SensorSample,
    rng: np.random.Generator,
    *,
    principal_point: tuple[float, float] | None = None,
) -> np.ndarray:
    """Camera output (H, W, 3) uint8 sRGB from a linear image (H, W, 3) float32 in [0, 1]."""
    h, w = linear.shape[:2]
    x = np.array(linear, dtype=np.float32, copy=True)  # never modify the caller's image
    if sensor.defocus_radius_px > 0:
        x = cv2.filter2D(x, -1, disk_kernel(sensor.defocus_radius_px), borderType=cv2.BORDER_REFLECT)
    if sensor.motion_blur_px > 0:
        k = line_kernel(sensor.motion_blur_px, sensor.motion_blur_angle_deg)
        x = cv2.filter2D(x, -1, k, borderType=cv2.BORDER_REFLECT)
    if sensor.vignetting > 0:
        cx, cy = principal_point if principal_point is not None else (w / 2.0, h / 2.0)
        x = x * (1.0 - sensor.vignetting * _radius2(h, w, float(cx), float(cy)))[..., None]
    lum = x @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    key = float(np.exp(np.mean(np.log(lum + 1e-3))))
    gain = float(np.clip(MID_GREY / key, 0.25, 16.0)) * 2.0**sensor.exposure_ev
    x *= gain
    noise = rng.standard_normal(x.shape, dtype=np.float32)
    sigma = np.sqrt(np.maximum(x, 0.0) * sensor.shot_noise**2 + sensor.read_noise**2)
    x += sigma * noise
    idx = np.clip(x * _LUT_SCALE, 0, _LUT_SIZE - 1).astype(np.int32)
    out = _tone_lut()[idx]
    if sensor.jpeg_quality > 0:
        ok, buf = cv2.imencode(".jpg", out[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(sensor.jpeg_quality)])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        out = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
    return np.ascontiguousarray(out)
