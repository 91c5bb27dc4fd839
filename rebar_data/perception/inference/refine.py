"""The patch stages, each a small network reading the full-resolution patch around every detection.

- The second stage (:class:`Refiner`) moves each detection to where it places the crossing and gives the
  logit that the patch shows one at all, which lowers the scores of false detections.
- The crossing-point stage (:class:`CrossingPoint`) gives where each detection's 3D crossing point (the
  centerlines' midpoint, inside the steel) projects, from the patch and its viewing ray.
"""

from __future__ import annotations

from collections.abc import Callable
from fractions import Fraction

import cv2
import numpy as np

from rebar_data.errors import ConfigError

BORDERS = ("mirror", "mask")  # how a patch shows what lies beyond the image's border
# the patch's symmetries a refiner may average over, in the order ``views`` takes them: (flip rows, flip
# columns, swap the axes); a patch is centred on a pixel corner, so each is exact about its centre
SYMMETRIES = (
    (False, False, False),
    (True, True, False),  # a half turn
    (False, True, False),
    (True, False, False),
    (False, False, True),
    (True, True, True),
    (False, True, True),
    (True, False, True),
)
VIEWS = (1, 2, 4, 8)
# the resolutions a later pass reads a crossing at, by the size the first pass gives it (a refiner with a
# size output): at or below the first of ``shrink_above_px``, above it, above the second
SHRINKS = (1.0, 0.75, 0.5)


def _check_views(name: str, value: int) -> None:
    """ConfigError unless ``value`` is one of :data:`VIEWS` (``name`` says which setting it is)."""
    if value not in VIEWS:
        raise ConfigError(f"{name} = {value} is not accepted; accepted: one of {', '.join(map(str, VIEWS))}")


def turned(x: np.ndarray, symmetry: tuple[bool, bool, bool]) -> np.ndarray:
    """Patches (N, P, P, C) under one of :data:`SYMMETRIES` (rows flipped, columns flipped, then the axes
    swapped)."""
    rows, cols, swap = symmetry
    y = x[:, ::-1] if rows else x
    y = y[:, :, ::-1] if cols else y
    return y.transpose(0, 2, 1, 3) if swap else y


def turned_back(offset: np.ndarray, symmetry: tuple[bool, bool, bool]) -> np.ndarray:
    """(N, 2) offsets (du, dv) measured in patches under ``symmetry``, in the original patches' axes."""
    rows, cols, swap = symmetry
    d = offset[:, ::-1] if swap else offset
    return d * np.array([-1.0 if cols else 1.0, -1.0 if rows else 1.0])


def patches(
    image: np.ndarray, centres: np.ndarray, size: int, *, border: str = "mirror"
) -> tuple[np.ndarray, np.ndarray]:
    """Patches of ``image`` around each (u, v) of ``centres``, cut on the pixel grid.

    Each patch is centred on the pixel corner nearest its point, so it is a plain copy of pixels (no
    resampling: cutting 130 patches takes 0.1 ms instead of 2.4 ms with a sub-pixel warp, and the
    refiner scores the same either way); the refiner's offset is measured from that corner.

    Beyond the image's border, with ``border = "mirror"`` the pixels are mirrored (a crossing d pixels
    outside the frame then looks like one d pixels inside it); with ``"mask"`` they are 0 and each patch
    gets a fourth channel, 255 on the image and 0 beyond it, so a network can tell where the frame ends
    and place a crossing whose centre lies outside it (:class:`~rebar_data.perception.training.config.RefineConfig`
    ``border``). ``"mask"`` needs an (H, W, 3) uint8 image.

    Returns:
        (N, size, size, C) patches of the image's type (C = 3, or 4 with ``"mask"``; (N, size, size) for a
        one-channel (H, W) image, such as a depth image), and (N, 2) the corners they are centred on (COCO
        corner origin).
    """
    if border not in BORDERS:
        raise ConfigError(f"border = {border!r} is not accepted; accepted: one of {', '.join(BORDERS)}")
    centres = np.asarray(centres, float).reshape(-1, 2)
    h, w = image.shape[:2]
    half = size // 2
    corners = np.clip(np.floor(centres + 0.5), 0, [w, h]).astype(np.int64)
    if border == "mask" and (image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8):
        raise ConfigError(f"a masked patch needs an (H, W, 3) uint8 image, not {image.shape} {image.dtype}")
    mode = cv2.BORDER_CONSTANT if border == "mask" else cv2.BORDER_REFLECT
    padded = cv2.copyMakeBorder(image, half, half, half, half, mode, value=0)
    windows = np.lib.stride_tricks.sliding_window_view(padded, (size, size), axis=(0, 1))
    cut_out = windows[corners[:, 1], corners[:, 0]]  # (N, [C,] size, size): the window axes come last
    if cut_out.ndim == 4:
        cut_out = cut_out.transpose(0, 2, 3, 1)
    cut_out = np.ascontiguousarray(cut_out)
    if border == "mirror" or not len(cut_out):
        return cut_out, corners.astype(np.float64)
    # the mask as a fourth channel, 255 everywhere (OpenCV's RGB to RGBA on the patches: 0.1 ms for 50,
    # where numpy's strided copy takes 0.5), then 0 beyond the border in the few patches that reach it
    n = len(cut_out)
    out = cv2.cvtColor(cut_out.reshape(n * size, size, 3), cv2.COLOR_RGB2RGBA).reshape(n, size, size, 4)
    near = np.flatnonzero(((corners - half) < 0).any(axis=1) | ((corners + half) > [w, h]).any(axis=1))
    if len(near):
        offsets = np.arange(size) - half  # a patch's pixel k lies at corner + k - half
        cols = (corners[near, None, 0] + offsets >= 0) & (corners[near, None, 0] + offsets < w)  # (M, size)
        rows = (corners[near, None, 1] + offsets >= 0) & (corners[near, None, 1] + offsets < h)
        out[near, :, :, 3] = (rows[:, :, None] & cols[:, None, :]) * np.uint8(255)
    return out, corners.astype(np.float64)


def shrunk(image: np.ndarray, scale: int) -> tuple[np.ndarray, np.ndarray]:
    """``image`` shrunk ``scale`` times (area averaging, each side rounded), and the (2,) factors that take a
    point's (u, v) in ``image`` to the shrunk one (COCO corner origin in both)."""
    h, w = image.shape[:2]
    size = _shrunk_size(h, w, scale)
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), np.array([size[0] / w, size[1] / h])


def _shrunk_size(h: int, w: int, scale: float) -> tuple[int, int]:
    """(width, height) of an h x w image shrunk ``scale`` times, each side rounded."""
    return max(1, round(w / scale)), max(1, round(h / scale))


def shrunk_around(
    image: np.ndarray, centres: np.ndarray, scale: float, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """What :func:`shrunk` gives, computed only where ``size`` x ``size`` patches around ``centres`` (points
    in ``image``) read it in the shrunk image, and 0 elsewhere: the same pixels there, for a fraction of
    the work when the points are few (a 640 x 480 frame shrunk to 0.75 takes 0.64 ms whole).

    Area averaging at a factor p / q (lowest terms) maps each q x q block of pixels to a p x p block on
    its own, so each patch's region is widened to whole blocks and resized alone. Where the factor does
    not divide the image's sides into whole blocks, or ``scale`` is a whole number (OpenCV's own path for
    those shrinks a whole frame in about 0.06 ms), the whole image is shrunk (:func:`shrunk`)."""
    h, w = image.shape[:2]
    out_w, out_h = _shrunk_size(h, w, scale)
    factors = np.array([out_w / w, out_h / h])
    ratio = Fraction(out_w, w).limit_denominator(16)  # blocks of at most 16 pixels a side
    p, q = ratio.numerator, ratio.denominator
    if Fraction(out_h, h) != ratio or Fraction(out_w, w) != ratio or p == 1:
        return shrunk(image, scale)
    canvas = np.zeros((out_h, out_w) + image.shape[2:], image.dtype)
    centres = np.asarray(centres, float).reshape(-1, 2)
    if not len(centres):
        return canvas, factors
    half = size // 2
    # each patch's window in the shrunk image (as :func:`patches` cuts it), widened to whole blocks
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
    """A loaded refiner: ``refine(image, uv) -> uv`` moves each point to the crossing the patch shows;
    ``refine_and_verify`` also gives each point's verification logit when the refiner has one
    (``verifies``). With ``views`` > 1 it reads each patch also turned and flipped (the first ``views`` of
    :data:`SYMMETRIES`, in one batch) and averages the offsets, turned back: the network trained on
    patches turned and flipped alike, so each view is another draw of its placement errors. The
    verification logit stays the plain view's (averaged too, it lowered recall at precision 0.99 on the
    curved Cycles set: :class:`~rebar_data.perception.training.config.RefineConfig` ``views``). The first pass
    reads ``first_pass_views`` views (None: ``views``).

    With ``iterations`` > 1 each later pass reads the patch centred where the pass before placed the
    crossing and moves the point ``step`` of the way to where it places it (1: all the way); the
    verification logit stays the first pass's (``RefineConfig.iterations`` and ``step``: why two passes,
    half a step). A refiner with a size output (``sizes``) also gives, in the first pass, each crossing's
    box side (four bar diameters); with ``shrink_above_px`` the later passes read a crossing seen larger
    than its first size from the image shrunk to 0.75, larger than the second to 0.5 (:data:`SHRINKS`), so
    that the patch shows all of it (``RefineConfig.size``). With ``int8_run`` the passes after the first
    read another copy of the network, an int8 one (``RefineConfig.quantize = "later"``): the first pass,
    whose verification every score counts and whose sizes choose the later passes' resolution, stays
    in float."""

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
        first_pass_views = views if first_pass_views is None else first_pass_views
        _check_views("views", views)
        _check_views("first_pass_views", first_pass_views)
        if not 0.0 < step <= 1.0:
            raise ConfigError(f"step = {step} is not accepted; accepted: a number above 0, at most 1")
        self._run = run
        self._int8_run = int8_run
        # whether the passes after the first read the int8 copy (False: the float network, for comparing)
        self.use_int8_passes = int8_run is not None
        self.views = views
        self.first_pass_views = first_pass_views
        self.step = step
        self.patch_px = patch_px
        self.iterations = iterations
        self.verifies = verifies
        self.sizes = sizes
        self.shrink_above_px = tuple(shrink_above_px) if shrink_above_px is not None else None

    @property
    def has_int8_passes(self) -> bool:
        """Whether this refiner has an int8 copy for the passes after the first."""
        return self._int8_run is not None

    def refine(self, image: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(N, 2) refined positions of the (N, 2) points ``uv`` in ``image`` (pixels, COCO corner origin)."""
        return self.refine_and_verify(image, uv)[0]

    def refine_and_verify(
        self,
        image: np.ndarray,
        uv: np.ndarray,
        *,
        keep: Callable[[np.ndarray], np.ndarray] | None = None,
        later_views: int | None = None,
        int8_first_pass: bool = False,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The refined positions (N, 2) and, when the refiner verifies, (N,) logits that each point's
        first patch (centred where the first stage put it) shows a crossing; None otherwise.

        ``keep`` (for a refiner that verifies) takes the first pass's logits and says which points the
        later passes go on moving; the others stay where the first pass placed them (the detector drops
        those its verification has already put under its threshold, so their later passes are spared).
        ``later_views``: the views the later passes read (None: ``views``); ``int8_first_pass``: the first
        pass reads the int8 copy too, where the later passes do (the detector's mirrored reading)."""
        if later_views is not None:
            _check_views("later_views", later_views)
        uv = np.asarray(uv, np.float64).reshape(-1, 2).copy()
        if not len(uv):
            return uv, (np.zeros(0) if self.verifies else None)
        corners, out = self._read_at(image, uv, self.first_pass_views, int8=int8_first_pass)
        logit = out[:, 2].copy() if self.verifies else None
        box = None  # the first pass's sizes, when later passes read by them
        if self.sizes and self.shrink_above_px is not None:
            box = self.patch_px * np.exp(out[:, 3])
        uv = corners + out[:, :2]
        moving = slice(None)  # the points the later passes move: all, or those ``keep`` names
        if self.iterations > 1 and keep is not None and logit is not None:
            moving = np.asarray(keep(logit), bool)
        uv[moving] = self._later_passes(image, uv[moving], None if box is None else box[moving], later_views)
        return uv, logit

    def _later_passes(
        self, image: np.ndarray, uv: np.ndarray, box: np.ndarray | None, views: int | None = None
    ) -> np.ndarray:
        """``uv`` moved by the passes after the first (each ``step`` of the way to where it places them),
        each read in ``views`` views (None: ``self.views``)."""
        for _ in range(1, self.iterations):
            if not len(uv):
                break
            uv = uv + self.step * (self._placed_at_size(image, uv, box, views) - uv)
        return uv

    def box_sizes(self, image: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(N,) each point's crossing's box side in pixels (four bar diameters), as the patch centred there
        shows it; needs a refiner with a size output."""
        if not self.sizes:
            raise ConfigError("this refiner has no size output; accepted: one trained with size: true")
        return self.patch_px * np.exp(self._read_at(image, uv, self.first_pass_views)[1][:, 3])

    def _read_at(
        self, image: np.ndarray, uv: np.ndarray, views: int | None = None, *, int8: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """The corners the patches around ``uv`` are centred on, and the network's output for them, read in
        ``views`` views (None: ``self.views``), by the int8 copy with ``int8`` (where there is one and
        ``use_int8_passes`` is on)."""
        x, corners = self._inputs_at(image, uv)
        return corners, self._read(x, self.views if views is None else views, self._runner(int8))

    def _inputs_at(self, image: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What this network reads around each of ``uv`` in ``image``, and the corners its patches are
        centred on (:func:`patches` with its patch size and the border mask)."""
        return patches(image, uv, self.patch_px, border="mask")

    def _runner(self, int8: bool) -> Callable[[np.ndarray], np.ndarray]:
        """The network a pass reads: the int8 copy with ``int8`` (where there is one and ``use_int8_passes``
        is on), the float one otherwise."""
        return self._int8_run if int8 and self.use_int8_passes and self._int8_run is not None else self._run

    def _placed_at_size(
        self, image: np.ndarray, uv: np.ndarray, box: np.ndarray | None, views: int | None = None
    ) -> np.ndarray:
        """Where each point's patch places its crossing, read in ``views`` views (None: ``self.views``) at
        the resolution of :data:`SHRINKS` its box side ``box`` calls for (None: all at full resolution).
        The patches of every resolution go through the network in one call (each call costs about what
        ten more patches do)."""
        if box is None:
            corners, out = self._read_at(image, uv, views, int8=True)
            return corners + out[:, :2]
        lo, hi = self.shrink_above_px
        level = (box > lo).astype(int) + (box > hi)
        picks, inputs, shifts = [], [], []  # per resolution read: its points, patches, corner-to-image map
        for lv, f in enumerate(SHRINKS):
            pick = np.flatnonzero(level == lv)
            if not len(pick):
                continue
            if f == 1.0:
                img, factors = image, np.ones(2)
            else:
                img, factors = shrunk_around(image, uv[pick], 1.0 / f, self.patch_px)
            x, corners = self._inputs_at(img, uv[pick] * factors)
            picks.append(pick)
            inputs.append(x)
            shifts.append((corners, factors))
        out = self._read(
            np.concatenate(inputs) if len(inputs) > 1 else inputs[0],
            self.views if views is None else views,
            self._runner(True),
        )
        placed = np.empty_like(uv)
        start = 0
        for pick, (corners, factors) in zip(picks, shifts, strict=True):
            placed[pick] = (corners + out[start : start + len(pick), :2]) / factors
            start += len(pick)
        return placed

    def _read(self, x: np.ndarray, views: int, run: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """The output of the network ``run`` for patches ``x``: the offsets averaged over ``views`` views
        (turned back), the rest the plain view's."""
        if views == 1:
            return run(x).astype(np.float64)
        sym = SYMMETRIES[:views]
        out = run(np.ascontiguousarray(np.concatenate([turned(x, s) for s in sym]))).astype(np.float64)
        out = out.reshape(views, len(x), -1)
        plain = out[0].copy()  # SYMMETRIES[0] is the identity
        plain[:, :2] = np.mean([turned_back(o[:, :2], s) for o, s in zip(out, sym, strict=True)], axis=0)
        return plain


# what a detection's pixel stands for: the sight point (where the image shows the bars cross, the
# dataset's labels) or the projected 3D crossing point (this stage's output)
POINTS = ("sight", "crossing")


def patch_rays(corners: np.ndarray, camera: tuple[float, float, float, float]) -> np.ndarray:
    """(N, 2) float32 viewing ray ((u - cx) / fx, (v - cy) / fy) of each patch centre (pixel corner)."""
    fx, fy, cx, cy = camera
    c = np.asarray(corners, np.float64).reshape(-1, 2)
    return np.c_[(c[:, 0] - cx) / fx, (c[:, 1] - cy) / fy].astype(np.float32)


class CrossingPoint:
    """A loaded crossing-point stage: ``offsets(image, uv, camera)`` gives, for each sight point ``uv``, the
    (N, 2) pixel offset to where its 3D crossing point projects."""

    def __init__(self, run: Callable[[np.ndarray, np.ndarray], np.ndarray], *, patch_px: int):
        self._run = run
        self.patch_px = patch_px

    def offsets(
        self, image: np.ndarray, uv: np.ndarray, camera: tuple[float, float, float, float]
    ) -> np.ndarray:
        """(N, 2) offsets from the (N, 2) sight points ``uv`` of the RGB ``image`` (pixels, COCO corner
        origin) to their projected 3D crossing points; ``camera`` is (fx, fy, cx, cy)."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        if not len(uv):
            return np.zeros((0, 2))
        x, corners = patches(image, uv, self.patch_px)
        return self._run(x, patch_rays(corners, camera)).astype(np.float64)

    def points(
        self, image: np.ndarray, uv: np.ndarray, camera: tuple[float, float, float, float]
    ) -> np.ndarray:
        """(N, 2) projected 3D crossing points of the sight points ``uv``."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        return uv + self.offsets(image, uv, camera)


def check_point(point: str) -> str:
    """``point`` if it is one of :data:`POINTS`, else ConfigError."""
    if point not in POINTS:
        raise ConfigError(f"point = {point!r} is not accepted; accepted: one of {', '.join(POINTS)}")
    return point
