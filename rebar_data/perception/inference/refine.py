"""The patch stages: :class:`Refiner` (the second stage) moves each detection onto its crossing and verifies
it; :class:`CrossingPoint` gives where each detection's 3D crossing point projects."""

from __future__ import annotations

from collections.abc import Callable
from fractions import Fraction

import cv2
import numpy as np

from rebar_data.camera import Intrinsics
from rebar_data.errors import ConfigError

BORDERS = ("mirror", "mask")  # how a patch shows what lies beyond the image's border
# (flip rows, flip columns, swap axes) in the order ``views`` takes them; exact about a patch's centre corner:
# as it is, turned half a turn, mirrored left to right, upside down; then each of those transposed
_FLIPS = ((False, False), (True, True), (False, True), (True, False))
SYMMETRIES = tuple((rows, cols, swap) for swap in (False, True) for rows, cols in _FLIPS)
SHRINKS = (1.0, 0.75, 0.5)  # a later pass's resolution by the crossing's size against ``shrink_above_px``


def accepted(name: str, value, choices: tuple) -> None:
    """ConfigError naming ``name`` unless ``value`` is one of ``choices``."""
    if value not in choices:
        shown = repr(value) if isinstance(value, str) else value
        raise ConfigError(
            f"{name} = {shown} is not accepted; accepted: one of {', '.join(map(str, choices))}"
        )


def patches(
    image: np.ndarray, centres: np.ndarray, size: int, *, border: str = "mirror"
) -> tuple[np.ndarray, np.ndarray]:
    """(N, size, size[, C]) patches of ``image`` centred on the pixel corner nearest each (u, v) of
    ``centres``, and (N, 2) those corners. Beyond the border the pixels are mirrored (``"mirror"``), or 0 with
    a fourth channel, 255 on the image and 0 beyond it (``"mask"``, for an (H, W, 3) uint8 image)."""
    accepted("border", border, BORDERS)
    centres = np.asarray(centres, float).reshape(-1, 2)
    h, w = image.shape[:2]
    half = size // 2
    corners = np.clip(np.floor(centres + 0.5), 0, [w, h]).astype(np.int64)
    mode = cv2.BORDER_CONSTANT if border == "mask" else cv2.BORDER_REFLECT
    padded = cv2.copyMakeBorder(image, half, half, half, half, mode, value=0)
    windows = np.lib.stride_tricks.sliding_window_view(padded, (size, size), axis=(0, 1))
    cut_out = windows[corners[:, 1], corners[:, 0]]  # (N, [C,] size, size)
    if cut_out.ndim == 4:
        cut_out = cut_out.transpose(0, 2, 3, 1)
    cut_out = np.ascontiguousarray(cut_out)
    if border == "mirror" or not len(cut_out):
        return cut_out, corners.astype(np.float64)
    n = len(cut_out)
    out = cv2.cvtColor(cut_out.reshape(n * size, size, 3), cv2.COLOR_RGB2RGBA).reshape(n, size, size, 4)
    near = np.flatnonzero(((corners - half) < 0).any(axis=1) | ((corners + half) > [w, h]).any(axis=1))
    if len(near):
        offsets = np.arange(size) - half  # a patch's pixel k lies at corner + k - half
        cols = (corners[near, None, 0] + offsets >= 0) & (corners[near, None, 0] + offsets < w)
        rows = (corners[near, None, 1] + offsets >= 0) & (corners[near, None, 1] + offsets < h)
        out[near, :, :, 3] = (rows[:, :, None] & cols[:, None, :]) * np.uint8(255)
    return out, corners.astype(np.float64)


def shrunk(image: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``image`` shrunk ``scale`` times (area averaging), and the (2,) factors from its (u, v) to the new."""
    h, w = image.shape[:2]
    size = max(1, round(w / scale)), max(1, round(h / scale))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), np.array([size[0] / w, size[1] / h])


def shrunk_around(
    image: np.ndarray, centres: np.ndarray, scale: float, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`shrunk`, worked out only where ``size`` patches around ``centres`` read it (0 elsewhere): area
    averaging at a factor p / q maps each q x q block to a p x p block, so each patch's region, widened to
    whole blocks, is resized alone; where the factor is no such ratio the whole image is shrunk."""
    h, w = image.shape[:2]
    out_w, out_h = max(1, round(w / scale)), max(1, round(h / scale))
    factors = np.array([out_w / w, out_h / h])
    ratio = Fraction(out_w, w).limit_denominator(16)
    p, q = ratio.numerator, ratio.denominator
    if Fraction(out_h, h) != ratio or Fraction(out_w, w) != ratio or p == 1:
        return shrunk(image, scale)
    canvas = np.zeros((out_h, out_w) + image.shape[2:], image.dtype)
    centres = np.asarray(centres, float).reshape(-1, 2)
    half = size // 2
    corners = np.clip(np.floor(centres * factors + 0.5), 0, [out_w, out_h]).astype(np.int64)
    lo = np.clip(corners - half, 0, None) // p * p
    hi = np.minimum(-(-(corners + half) // p) * p, [out_w, out_h])
    for (x0, y0), (x1, y1) in zip(lo, hi, strict=True):
        if x1 <= x0 or y1 <= y0:
            continue
        block = image[y0 // p * q : y1 * q // p, x0 // p * q : x1 * q // p]
        canvas[y0:y1, x0:x1] = cv2.resize(block, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
    return canvas, factors


class Refiner:
    """The second stage: :meth:`first_pass` moves each point onto its crossing and gives its verification
    logit; each of the ``iterations`` - 1 :meth:`later_passes` moves ``step`` of the way to where the patch at
    the point places it, read by ``int8_run`` where given; ``views`` > 1 averages the offsets over turned and
    flipped patches (:data:`SYMMETRIES`); with ``sizes`` and ``shrink_above_px`` a later pass reads a large
    crossing from the image shrunk (:data:`SHRINKS`)."""

    def __init__(
        self,
        run: Callable[[np.ndarray], np.ndarray],
        *,
        patch_px: int,
        iterations: int,
        verifies: bool,
        views: int = 1,
        step: float = 1.0,
        sizes: bool = False,
        shrink_above_px: tuple[float, float] | None = None,
        first_pass_views: int | None = None,
        int8_run: Callable[[np.ndarray], np.ndarray] | None = None,
    ):
        self._run = run
        self.int8_run = int8_run
        self.views = views
        self.first_pass_views = views if first_pass_views is None else first_pass_views
        self.step = step
        self.patch_px = patch_px
        self.iterations = iterations
        self.verifies = verifies
        self.shrink_above_px = tuple(shrink_above_px) if sizes and shrink_above_px is not None else None

    def first_pass(
        self, image: np.ndarray, uv: np.ndarray, *, mirrored: bool = False
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(N, 2) positions of the N >= 1 points ``uv`` moved onto their crossings, their (N,) verification
        logits and (N,) box sides (each None where the stage has no such output). ``mirrored`` (the mirrored
        reading) reads the int8 copy where there is one."""
        x, corners = patches(image, uv, self.patch_px, border="mask")
        run = self.int8_run if mirrored and self.int8_run is not None else self._run
        out = self._read(x, self.first_pass_views, run)
        logit = out[:, 2] if self.verifies else None
        box = self.patch_px * np.exp(out[:, 3]) if self.shrink_above_px is not None else None
        return corners + out[:, :2], logit, box

    def later_passes(
        self, image: np.ndarray, uv: np.ndarray, box: np.ndarray | None, *, mirrored: bool = False
    ) -> np.ndarray:
        """``uv`` (N, 2) moved by the later passes, reading each point at the size its ``box`` side calls
        for; ``mirrored`` reads one view."""
        views = 1 if mirrored else self.views
        for _ in range(self.iterations - 1 if len(uv) else 0):
            uv = uv + self.step * (self._placed_at_size(image, uv, box, views) - uv)
        return uv

    def _placed_at_size(
        self, image: np.ndarray, uv: np.ndarray, box: np.ndarray | None, views: int
    ) -> np.ndarray:
        """Where each point's patch places its crossing, each read at the resolution its box side ``box``
        calls for (None: full resolution); every resolution's patches in one call."""
        run = self._run if self.int8_run is None else self.int8_run
        if box is None:
            x, corners = patches(image, uv, self.patch_px, border="mask")
            return corners + self._read(x, views, run)[:, :2]
        lo, hi = self.shrink_above_px
        level = (box > lo).astype(int) + (box > hi)
        picks, inputs, shifts = [], [], []
        for lv, f in enumerate(SHRINKS):
            pick = np.flatnonzero(level == lv)
            if not len(pick):
                continue
            if f == 1.0:
                img, factors = image, np.ones(2)
            else:
                img, factors = shrunk_around(image, uv[pick], 1.0 / f, self.patch_px)
            x, corners = patches(img, uv[pick] * factors, self.patch_px, border="mask")
            picks.append(pick)
            inputs.append(x)
            shifts.append((corners, factors))
        out = self._read(np.concatenate(inputs) if len(inputs) > 1 else inputs[0], views, run)
        placed = np.empty_like(uv)
        start = 0
        for pick, (corners, factors) in zip(picks, shifts, strict=True):
            placed[pick] = (corners + out[start : start + len(pick), :2]) / factors
            start += len(pick)
        return placed

    def _read(self, x: np.ndarray, views: int, run: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """``run`` on patches ``x``: the offsets averaged over ``views`` views, the rest the plain view's."""
        if views == 1:
            return run(x).astype(np.float64)
        sym = SYMMETRIES[:views]
        turned = []
        for rows, cols, swap in sym:
            y = x[:, ::-1] if rows else x
            y = y[:, :, ::-1] if cols else y
            turned.append(y.transpose(0, 2, 1, 3) if swap else y)
        out = run(np.ascontiguousarray(np.concatenate(turned))).astype(np.float64).reshape(views, len(x), -1)
        back = []  # each view's offsets (du, dv) in the plain patch's axes
        for o, (rows, cols, swap) in zip(out, sym, strict=True):
            d = o[:, 1::-1] if swap else o[:, :2]
            back.append(d * np.array([-1.0 if cols else 1.0, -1.0 if rows else 1.0]))
        plain = out[0].copy()
        plain[:, :2] = np.mean(back, axis=0)
        return plain


def patch_rays(corners: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """(N, 2) float32 viewing ray ((u - cx) / fx, (v - cy) / fy) of each patch centre."""
    return camera.normalized(np.asarray(corners, np.float64).reshape(-1, 2)).astype(np.float32)


class CrossingPoint:
    """The crossing-point stage: ``points(image, uv, camera)`` gives where each sight point's 3D crossing
    point projects, from its patch and viewing ray."""

    def __init__(self, run: Callable[[np.ndarray, np.ndarray], np.ndarray], *, patch_px: int):
        self._run = run
        self.patch_px = patch_px

    def points(self, image: np.ndarray, uv: np.ndarray, camera: Intrinsics) -> np.ndarray:
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        if not len(uv):
            return uv.copy()
        x, corners = patches(image, uv, self.patch_px)
        return uv + self._run(x, patch_rays(corners, camera)).astype(np.float64)
