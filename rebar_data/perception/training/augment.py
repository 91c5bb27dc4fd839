"""Training crops whose keypoints move exactly with the pixels.

Each crop is one random similarity map ``crop_from_image`` (2x3, COCO's corner origin) that moves the
keypoints and, converted to OpenCV's pixel-index convention, resamples the pixels; a mosaic fills the
four quadrants of a crop from four images. Photometric changes touch pixels only."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from rebar_data.perception.inference.detector import STRIDE
from rebar_data.perception.training.config import AugmentConfig

SEAM_PX = 3.0  # crossings this close to a mosaic seam are cut in two: neither positive nor negative


@dataclass
class Crop:
    """One training crop; points in crop pixels."""

    image: np.ndarray  # (S, S, 3) uint8 RGB
    positives: np.ndarray  # (N, 2) visible crossings
    ignore: np.ndarray  # (M, 2) points left out of the loss (occluded, or cut by a mosaic seam)
    rays: np.ndarray  # (2, S / 4, S / 4) each output cell's viewing ray (:func:`crop_rays`)


@dataclass
class Source:
    """One image to crop from: pixels, crossings, points to ignore, intrinsics (fx, fy, cx, cy)."""

    image: np.ndarray
    positives: np.ndarray
    ignore: np.ndarray
    camera: tuple[float, float, float, float]
    distractors: np.ndarray | None = None  # (H, W) bool: the distractors' pixels, when known
    gain: float = 1.0  # every crop's scale times this: a frame of another focal length drawn at the model's


def draw_gain(rng: np.random.Generator, cfg: AugmentConfig, distractors: np.ndarray | None) -> float | None:
    """The factor the distractors' pixels are scaled by this time (log-uniform in ``cfg.distractor_gain``),
    or None; draws nothing when the share is 0 or the pixels are unknown."""
    if distractors is None or not cfg.scales_distractors or rng.uniform() >= cfg.distractor_gain_probability:
        return None
    lo, hi = np.log(cfg.distractor_gain)
    return float(np.exp(rng.uniform(lo, hi)))


def scaled_where(image: np.ndarray, where: np.ndarray, gain: float | None) -> np.ndarray:
    """``image`` with its colour at the ``where`` pixels times ``gain`` (a copy); itself for None."""
    if gain is None:
        return image
    out = image.copy()
    rgb = out[..., :3]
    rgb[where] = np.clip(rgb[where] * np.float32(gain), 0, 255).astype(np.uint8)
    return out


def distractor_gain(
    image: np.ndarray, distractors: np.ndarray | None, rng: np.random.Generator, cfg: AugmentConfig
) -> np.ndarray:
    """``image`` with the ``distractors`` pixels (H, W bool) scaled by :func:`draw_gain`'s factor."""
    return scaled_where(image, distractors, draw_gain(rng, cfg, distractors))


def apply_affine(points: np.ndarray, crop_from_image: np.ndarray) -> np.ndarray:
    """Map (N, 2) points with a 2x3 affine map."""
    p = np.asarray(points, float).reshape(-1, 2)
    return p @ crop_from_image[:, :2].T + crop_from_image[:, 2]


def warp(image: np.ndarray, crop_from_image: np.ndarray, size: int, *, fill: float | None) -> np.ndarray:
    """Resample ``image`` into a ``size`` square (bilinear); outside it the constant ``fill``, or for None
    the image mirrored (so no edge looks like a bar)."""
    m = np.asarray(crop_from_image, float).copy()  # for OpenCV, whose pixel (i, j) is (i + 0.5, j + 0.5)
    m[:, 2] += m[:, :2] @ [0.5, 0.5] - 0.5
    border, value = (cv2.BORDER_REFLECT, (0, 0, 0)) if fill is None else (cv2.BORDER_CONSTANT, (fill,) * 3)
    return cv2.warpAffine(
        image, m, (size, size), flags=cv2.INTER_LINEAR, borderMode=border, borderValue=value
    )


def crop_rays(
    crop_from_image: np.ndarray, size: int, camera: tuple[float, float, float, float], *, stride: int = STRIDE
) -> np.ndarray:
    """(2, S / stride, S / stride) viewing rays of the crop's output-cell centres in the virtual camera that
    films the crop: the source rays of the same points, turned and flipped with the pixels (a similarity
    crop of a pinhole image is a pinhole camera's image, turned about its optical axis)."""
    fx, fy, cx, cy = camera
    lin, t = crop_from_image[:, :2], crop_from_image[:, 2]
    inv = np.linalg.inv(lin)
    c = stride * (np.arange(size // stride, dtype=np.float64) + 0.5)
    qx, qy = np.meshgrid(c - t[0], c - t[1], indexing="xy")
    px = inv[0, 0] * qx + inv[0, 1] * qy
    py = inv[1, 0] * qx + inv[1, 1] * qy
    rx, ry = (px - cx) / fx, (py - cy) / fy  # rays in the source camera
    turn = lin / np.sqrt(abs(np.linalg.det(lin)))  # rotation and flips of the crop, scale removed
    return np.stack([turn[0, 0] * rx + turn[0, 1] * ry, turn[1, 0] * rx + turn[1, 1] * ry]).astype(np.float32)


def random_affine(
    rng: np.random.Generator, *, centre: np.ndarray, target: np.ndarray, cfg: AugmentConfig, gain: float = 1.0
) -> np.ndarray:
    """A random similarity (scale times ``gain``, rotation, flips) taking ``centre`` to ``target``."""
    lo, hi = cfg.scale
    s = gain * float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    a = np.radians(rng.uniform(-cfg.rotation_deg, cfg.rotation_deg))
    fx = -1.0 if rng.uniform() < cfg.flip_lr else 1.0
    fy = -1.0 if rng.uniform() < cfg.flip_ud else 1.0
    lin = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ np.diag([fx, fy])
    return np.c_[lin, np.asarray(target, float) - lin @ np.asarray(centre, float)]


def _inside(
    points: np.ndarray, x0: float, y0: float, x1: float, y1: float, margin: float = 0.0
) -> np.ndarray:
    return ((points >= [x0 + margin, y0 + margin]) & (points < [x1 - margin, y1 - margin])).all(axis=1)


def single_crop(src: Source, rng: np.random.Generator, *, size: int, cfg: AugmentConfig) -> Crop:
    """A crop around a random point of one image, with random scale, rotation and flips."""
    h, w = src.image.shape[:2]
    centre = np.array([rng.uniform(0, w), rng.uniform(0, h)])
    target = np.array([size / 2, size / 2])
    crop_from_image = random_affine(rng, centre=centre, target=target, cfg=cfg, gain=src.gain)
    fill = float(rng.uniform(0, 255))
    out = warp(distractor_gain(src.image, src.distractors, rng, cfg), crop_from_image, size, fill=fill)
    pos = apply_affine(src.positives, crop_from_image)
    ign = apply_affine(src.ignore, crop_from_image)
    keep = _inside(pos, 0, 0, size, size)
    rays = crop_rays(crop_from_image, size, src.camera)
    return Crop(out, pos[keep], ign[_inside(ign, -8, -8, size + 8, size + 8)], rays)


def mosaic_crop(
    pick: Callable[[], Source], rng: np.random.Generator, *, size: int, cfg: AugmentConfig
) -> Crop:
    """Four images (``pick`` gives one a call) in the four quadrants of one crop, split at a random point."""
    xc, yc = rng.uniform(0.25, 0.75, 2) * size
    canvas = np.empty((size, size, 3), np.uint8)
    rays = np.empty((2, size // STRIDE, size // STRIDE), np.float32)
    cell = STRIDE * (np.arange(size // STRIDE) + 0.5)
    pos_all, ign_all = [], []
    fill = float(rng.uniform(0, 255))
    for x0, y0, x1, y1 in ((0, 0, xc, yc), (xc, 0, size, yc), (0, yc, xc, size), (xc, yc, size, size)):
        src = pick()
        h, w = src.image.shape[:2]
        centre = np.array([rng.uniform(0, w), rng.uniform(0, h)])
        crop_from_image = random_affine(
            rng, centre=centre, target=np.array([(x0 + x1) / 2, (y0 + y1) / 2]), cfg=cfg, gain=src.gain
        )
        full = warp(distractor_gain(src.image, src.distractors, rng, cfg), crop_from_image, size, fill=fill)
        i0, i1, j0, j1 = round(y0), round(y1), round(x0), round(x1)
        canvas[i0:i1, j0:j1] = full[i0:i1, j0:j1]
        # the output cells whose centre lies in the pasted region
        pasted = ((cell >= i0) & (cell < i1))[:, None] & ((cell >= j0) & (cell < j1))[None, :]
        rays[:, pasted] = crop_rays(crop_from_image, size, src.camera)[:, pasted]
        x0, y0, x1, y1 = j0, i0, j1, i1  # the region actually pasted
        pos = apply_affine(src.positives, crop_from_image)
        inside = _inside(pos, x0, y0, x1, y1)
        clear = _inside(pos, x0, y0, x1, y1, margin=SEAM_PX) | ~_inside(pos, 0, 0, size, size, margin=SEAM_PX)
        pos_all.append(pos[inside & clear])
        ign_all.append(pos[inside & ~clear])
        ign = apply_affine(src.ignore, crop_from_image)
        ign_all.append(ign[_inside(ign, x0 - 8, y0 - 8, x1 + 8, y1 + 8)])
    return Crop(canvas, np.concatenate(pos_all).reshape(-1, 2), np.concatenate(ign_all).reshape(-1, 2), rays)


def photometric(image: np.ndarray, rng: np.random.Generator, cfg: AugmentConfig) -> np.ndarray:
    """Random brightness, contrast, saturation, hue, white balance, gamma, blur and noise (pixels only)."""
    return photometric_batch(image[None], rng, cfg)[0]


def photometric_batch(images: np.ndarray, rng: np.random.Generator, cfg: AugmentConfig) -> np.ndarray:
    """:func:`photometric` for (N, H, W, 3) uint8 images, each with its own changes; each change is drawn
    for all N before the next, in the single image's number types."""
    n = len(images)
    img = images.astype(np.float32)
    if cfg.hue_deg > 0 or cfg.saturation > 0 or cfg.hue_full_probability > 0:
        hsv = cv2.cvtColor(images.reshape(-1, *images.shape[2:]), cv2.COLOR_RGB2HSV_FULL)
        hsv = hsv.reshape(images.shape).astype(np.float32)
        hue = (rng.uniform(-cfg.hue_deg, cfg.hue_deg, n) * 256 / 360).astype(np.float32)
        if cfg.hue_full_probability > 0:
            turned = rng.uniform(size=n) < cfg.hue_full_probability
            hue = np.where(turned, rng.uniform(0, 256, n), hue).astype(np.float32)
        hsv[..., 0] = (hsv[..., 0] + hue[:, None, None]) % 256
        hsv[..., 1] *= (1 + rng.uniform(-cfg.saturation, cfg.saturation, n)).astype(np.float32)[:, None, None]
        rgb = np.clip(hsv, 0, 255).astype(np.uint8).reshape(-1, *images.shape[2:])
        img = cv2.cvtColor(rgb, cv2.COLOR_HSV2RGB_FULL).reshape(images.shape).astype(np.float32)
    if cfg.white_balance > 0:
        gains = 1 + rng.uniform(-cfg.white_balance, cfg.white_balance, (n, 3))
        img *= gains.astype(np.float32)[:, None, None, :]
    mean = np.array([x.mean() for x in img], np.float32)[:, None, None, None]  # as each image alone
    contrast = (1 + rng.uniform(-cfg.contrast, cfg.contrast, n)).astype(np.float32)[:, None, None, None]
    img = (img - mean) * contrast + mean
    img *= (1 + rng.uniform(-cfg.brightness, cfg.brightness, n)).astype(np.float32)[:, None, None, None]
    gamma = np.exp(rng.uniform(-cfg.gamma, cfg.gamma, n))[:, None, None, None]
    img = 255.0 * (np.clip(img, 0, 255) / 255.0) ** gamma  # float64 from here, as for one image
    blurred = np.flatnonzero(rng.uniform(size=n) < cfg.blur_probability)
    for i, sigma in zip(blurred, rng.uniform(*cfg.blur_sigma_px, len(blurred)), strict=True):
        img[i] = cv2.GaussianBlur(img[i], (0, 0), max(1e-3, sigma))
    noisy = np.flatnonzero(rng.uniform(size=n) < cfg.noise_probability)
    if len(noisy):
        std = rng.uniform(*cfg.noise_std, len(noisy))[:, None, None, None]
        img[noisy] += (rng.standard_normal((len(noisy), *img.shape[1:])) * std).astype(np.float32)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)
