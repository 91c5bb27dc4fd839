"""The checks that score each detection again: :class:`DepthCheck`, a small network reading the depth patch
around it, and (without depth) :class:`LineCheck`, a logistic regression on the scores of the candidates
along its two bars (:data:`FEATURES`) and its own."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import cv2
import numpy as np

from rebar_data.errors import ConfigError
from rebar_data.perception.inference.refine import patches

CENTRE_PX = 4  # the patch's central square whose median depth is the reference
MM_PER_M = 1000.0


def as_depth_m(depth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``depth`` ((H, W) float metres or uint16 millimetres, registered to an image of ``shape``) as float32
    metres, 0 where there is no measurement (0, negative or not finite)."""
    d = np.asarray(depth)
    if d.ndim != 2 or d.shape != tuple(shape):
        raise ConfigError(
            f"depth image of shape {d.shape} is not accepted; accepted: an (H, W) array registered to the "
            f"colour image, here {tuple(shape)}"
        )
    if d.dtype == np.uint16:
        return d.astype(np.float32) / MM_PER_M
    if not np.issubdtype(d.dtype, np.floating):
        raise ConfigError(
            f"depth image of type {d.dtype} is not accepted; accepted: float metres or uint16 millimetres"
        )
    out = np.array(d, dtype=np.float32, copy=True)
    out[~(out > 0)] = 0.0  # negative, zero and NaN
    out[np.isinf(out)] = 0.0
    return out


def encode_depth(
    depth_patches: np.ndarray, *, scale_m: float, clip: float, gain: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2, P, P) float32 network input for (N, P, P) depth patches in metres (0 = none): the depth relative
    to the median of the central :data:`CENTRE_PX` square over ``scale_m`` (times ``gain``), clipped to
    +-``clip``, and 1 where measured; and (N,) whether each patch's centre holds a measurement."""
    p = np.asarray(depth_patches, np.float32)
    n, size = p.shape[0], p.shape[1]
    lo = size // 2 - CENTRE_PX // 2
    centre = p[:, lo : lo + CENTRE_PX, lo : lo + CENTRE_PX].reshape(n, -1)
    measured = (centre > 0).sum(axis=1)
    has_centre = measured > 0
    # the median of each row's measurements: sorted with the missing ones last
    ordered = np.sort(np.where(centre > 0, centre, np.inf), axis=1)
    rows = np.arange(n)
    a = np.maximum(measured - 1, 0) // 2
    b = np.minimum(np.maximum(measured, 1) // 2, ordered.shape[1] - 1)
    ref = np.where(has_centre, 0.5 * (ordered[rows, a] + ordered[rows, b]), 0.0).astype(np.float32)
    valid = p > 0
    rel = p - ref[:, None, None]
    rel *= np.float32(1.0 / scale_m)
    if gain is not None:
        rel *= np.asarray(gain, np.float32).reshape(n, 1, 1)
    np.clip(rel, -clip, clip, out=rel)
    rel[~valid] = 0.0
    share = valid.astype(np.float32)
    out = np.empty((n, 2, *rel.shape[1:]), np.float32)
    out[:, 0], out[:, 1] = rel, share
    return out, has_centre


# how a depth check's logit d lowers a score: by VETO_POWER * share**2 * min(0, d + VETO_MARGIN), share the
# part of its patch measured; a sensor's smoothed or missing depth may doubt a true crossing, so only a
# confident doubt over a mostly measured patch counts (docs/detector/experiments.md)
VETO_POWER = 0.5
VETO_MARGIN = 2.0


class DepthCheck:
    """The depth check: ``logits(depth_m, uv)``, each point's logit that the depth around it shows a crossing
    (+inf where the patch's centre holds no measurement), and the share of its patch measured; ``veto``, the
    logit shift each score takes from it (0 or less)."""

    def __init__(
        self,
        run: Callable[[np.ndarray], np.ndarray],
        *,
        patch_px: int,
        scale_m: float,
        clip: float,
        power: float = VETO_POWER,
        margin: float = VETO_MARGIN,
    ):
        self._run = run
        self.patch_px, self.scale_m, self.clip = patch_px, scale_m, clip
        self.power, self.margin = power, margin

    def logits(self, depth_m: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        out = np.full(len(uv), np.inf)
        if not len(uv):
            return out, np.zeros(0)
        x, has_centre = encode_depth(
            patches(depth_m, uv, self.patch_px)[0], scale_m=self.scale_m, clip=self.clip
        )
        if has_centre.any():
            out[has_centre] = self._run(np.ascontiguousarray(x[has_centre])).astype(np.float64).reshape(-1)
        return out, x[:, 1].mean(axis=(1, 2), dtype=np.float64)

    def veto(self, depth_m: np.ndarray, uv: np.ndarray) -> np.ndarray:
        logit, share = self.logits(depth_m, uv)
        doubt = np.minimum(0.0, np.where(np.isfinite(logit), logit, 0.0) + self.margin)
        return self.power * share**2 * doubt


FLOOR = 0.05  # candidates the first stage scores this or more are evidence
CHECKED_FROM = 0.3  # those it scores this or more are verified and checked
# how the bars are read: a fitted check's weights depend on it, and a file fitted with another is refused
READING = {
    "radius_px": 40,  # the bar directions are read within this many pixels of a candidate
    "bins": 60,  # edge orientations, 3 degrees a bin over 180
    "min_apart_deg": 25.0,  # the second bar direction is this far from the first at least
    "cone_deg": 4.0,
    "lateral_px": 2.0,
    "max_step_px": 260.0,
    "min_step_px": 5.0,
    "steps": 6,  # along each bar, each way
    "high": 0.8,
}
RADIUS_PX, BINS, MIN_APART_DEG, CONE_DEG, LATERAL_PX, MAX_STEP_PX, MIN_STEP_PX, STEPS, HIGH = READING.values()
_SUMMARY = ("count", "mean", "upper_quartile", "best", "share_high", "share_above_own", "best_two")
FEATURES = ("own_logit", *(f"{bar}_{s}" for bar in ("better_bar", "other_bar") for s in _SUMMARY))
_LOGIT_CLIP = 1e-3
_TAN = float(np.tan(np.deg2rad(CONE_DEG)))
_MODULO = (np.arange(256) % BINS).astype(np.uint8)  # orientation bins past 180 degrees folded back
_EVERY_OTHER = np.arange(0, RADIUS_PX, 2)  # the pixels of a half-resolution window read, along each side


def logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(np.asarray(p, np.float64), _LOGIT_CLIP, 1 - _LOGIT_CLIP)
    return np.log(p / (1 - p))


def bar_directions(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N, 2) angles (radians, v down) of the two bars at each of ``uv``, the stronger first: the peaks of
    the gradient orientation histogram within :data:`RADIUS_PX`, at half resolution."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if not len(uv):
        return np.zeros((0, 2))
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    gray = cv2.resize(gray, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA).astype(np.float32)
    h, w = gray.shape
    mag, ang = cv2.cartToPolar(
        cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3),
        cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3),
        angleInDegrees=True,
    )
    bins = cv2.LUT(cv2.convertScaleAbs(ang, alpha=BINS / 180.0), _MODULO)
    r = RADIUS_PX // 2
    bins = cv2.copyMakeBorder(bins, r, r, r, r, cv2.BORDER_CONSTANT, value=0)
    mag = cv2.copyMakeBorder(mag, r, r, r, r, cv2.BORDER_CONSTANT, value=0.0)  # beyond the image: no edges
    # a window's corner in the bordered images is its centre's pixel at half resolution
    centre = np.floor(uv / 2).astype(np.int64)
    top = np.clip(centre[:, 1], 0, h)
    left = np.clip(centre[:, 0], 0, w)
    # every other pixel of each window
    rows = (top[:, None] + _EVERY_OTHER)[:, :, None]
    cols = (left[:, None] + _EVERY_OTHER)[:, None, :]
    b = bins[rows, cols].astype(np.int64) + BINS * np.arange(len(uv))[:, None, None]
    hist = np.bincount(b.ravel(), mag[rows, cols].ravel(), len(uv) * BINS).reshape(len(uv), BINS)
    # smoothed over five bins, weights 1 2 3 2 1, around the circle
    ring = np.concatenate([hist[:, -2:], hist, hist[:, :2]], axis=1)  # ring[:, i + 2] is hist[:, i]
    hist = ring[:, 4:] + 2 * ring[:, 3:-1] + 3 * ring[:, 2:-2] + 2 * ring[:, 1:-3] + ring[:, :-4]
    first = np.argmax(hist, axis=1)
    apart = np.abs((np.arange(BINS)[None, :] - first[:, None] + BINS / 2) % BINS - BINS / 2)
    second = np.argmax(np.where(apart >= BINS * MIN_APART_DEG / 180.0, hist, -1.0), axis=1)
    normals = np.stack([first, second], axis=1) * (np.pi / BINS)
    return normals + np.pi / 2  # a bar runs across its edges' gradient


def bar_members(uv: np.ndarray, directions: np.ndarray, which: np.ndarray | None = None) -> np.ndarray:
    """(K, 2, 2 * STEPS) the candidates of ``uv`` met following both ways the two bars (angles ``directions``,
    K x 2) of each candidate ``which`` names (None: all), -1 past a bar's last one."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    which = np.arange(len(uv)) if which is None else np.asarray(which, np.int64)
    k = len(which)
    if len(uv) < 2 or not k:
        return np.full((k, 2, 2 * STEPS), -1, np.int64)
    start = np.repeat(which, 4)  # chains: candidate, bar, way
    ang = np.repeat(np.asarray(directions, np.float64).reshape(-1), 2) + np.tile([0.0, np.pi], 2 * k)
    d = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    chain = np.arange(len(start))
    cur = start.copy()
    seen = np.zeros((len(start), len(uv)), bool)
    seen[chain, start] = True
    members = np.full((len(start), STEPS), -1, np.int64)
    for step in range(STEPS):
        vu = uv[None, :, 0] - uv[cur, 0][:, None]
        vv = uv[None, :, 1] - uv[cur, 1][:, None]
        along = vu * d[:, 0, None] + vv * d[:, 1, None]
        lateral = np.abs(vu * d[:, 1, None] - vv * d[:, 0, None])
        ok = (along > MIN_STEP_PX) & (along < MAX_STEP_PX) & (lateral < LATERAL_PX + _TAN * along)
        ok &= ~seen[chain]
        alive = ok.any(axis=1)
        if not alive.any():
            break
        nxt = np.argmin(np.where(ok, along, np.inf), axis=1)
        chain, cur, d, j = chain[alive], cur[alive], d[alive], nxt[alive]
        members[chain, step] = j
        seen[chain, j] = True
        seg = np.stack([uv[j, 0] - uv[cur, 0], uv[j, 1] - uv[cur, 1]], axis=1)
        seg /= np.linalg.norm(seg, axis=1, keepdims=True)
        d = seg if step else 0.5 * (d + seg)  # the first step only half-trusts the image's direction
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        cur = j
    return members.reshape(k, 2, 2 * STEPS)


def features(score: np.ndarray, members: np.ndarray, which: np.ndarray | None = None) -> np.ndarray:
    """(K, len(FEATURES)): for each candidate ``which`` names (None: all), its own score's logit and the
    summaries of the scores along its two bars (``members``), better bar first."""
    score = np.asarray(score, np.float64)
    which = np.arange(len(score)) if which is None else np.asarray(which, np.int64)
    k = len(which)
    if not k:
        return np.zeros((0, len(FEATURES)))
    has = members >= 0
    count = has.sum(axis=2)  # (K, 2)
    c = np.maximum(count, 1)
    s = np.where(has, score[np.where(has, members, 0)], 2.0)  # past a bar's end: above every score
    asc = np.sort(s, axis=2)  # the bar's scores ascending, then the fill
    own = score[which][:, None, None]
    at = 0.75 * (c - 1)  # the upper quartile, interpolated as numpy's quantile does
    lo = np.floor(at).astype(np.int64)
    hi = np.minimum(lo + 1, c - 1)
    a = np.take_along_axis(asc, lo[..., None], 2)[..., 0]
    b = np.take_along_axis(asc, hi[..., None], 2)[..., 0]
    best = np.take_along_axis(asc, (c - 1)[..., None], 2)[..., 0]
    second = np.take_along_axis(asc, np.maximum(c - 2, 0)[..., None], 2)[..., 0]
    finite = np.where(has, s, 0.0)
    per = np.stack(
        [
            count.astype(np.float64),
            finite.sum(axis=2) / c,
            a + (at - lo) * (b - a),
            best,
            (has & (s >= HIGH)).sum(axis=2) / c,
            (has & (s > own)).sum(axis=2) / c,
            np.where(count > 1, 0.5 * (best + second), best),
        ],
        axis=2,
    )  # (K, 2, 7)
    per = np.where((count > 0)[:, :, None], per, 0.0)
    swap = per[:, 1, 2] > per[:, 0, 2]  # better bar (upper quartile) first
    per[swap] = per[swap][:, ::-1]
    return np.concatenate([logit(score[which])[:, None], per.reshape(k, -1)], axis=1)


def line_features(image: np.ndarray, uv: np.ndarray, evidence: np.ndarray, which: np.ndarray) -> np.ndarray:
    """:func:`features` of the candidates ``which`` among ``uv`` scored ``evidence``, read in ``image``."""
    return features(evidence, bar_members(uv, bar_directions(image, uv[which]), which), which)


@dataclass(frozen=True)
class LineCheck:
    """A fitted line check: its logistic regression's ``weights`` (per :data:`FEATURES`) and ``bias``, and the
    first-stage scores it was fitted with (``floor``, ``checked_from``); :meth:`from_meta` reads it from a
    model file's meta entry (:func:`~rebar_data.perception.training.line_check.line_check_meta` writes it)."""

    weights: np.ndarray
    bias: float
    floor: float = FLOOR
    checked_from: float = CHECKED_FROM

    def scores(
        self,
        image: np.ndarray,
        uv: np.ndarray,
        evidence: np.ndarray,
        checked: np.ndarray,
        *,
        threshold: float,
    ) -> np.ndarray:
        """(K,) new scores of the candidates ``checked`` among ``uv`` scored ``evidence``; 0 for one that
        could not reach ``threshold`` whatever its bars show (not followed)."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        evidence = np.asarray(evidence, np.float64)
        checked = np.asarray(checked, np.int64)
        out = np.zeros(len(checked))
        w = self.weights[0]  # the highest logit the check can give: the lowest own score's when w < 0
        own = logit(evidence[checked] if w >= 0 else np.zeros(len(checked)))
        reach = w * own + self._most_from_bars + self.bias >= np.log(threshold / (1 - threshold))
        which = checked[reach]
        if len(which):
            x = line_features(image, uv, evidence, which)
            out[reach] = 1.0 / (1.0 + np.exp(-(x @ self.weights + self.bias)))
        return out

    @cached_property
    def _most_from_bars(self) -> float:
        """The most the bar summaries (in [0, 1], counts up to 2 * STEPS) can add to the logit."""
        hi = np.ones(len(FEATURES) - 1)
        hi[[FEATURES.index(f"{bar}_count") - 1 for bar in ("better_bar", "other_bar")]] = 2 * STEPS
        return float(np.maximum(0.0, self.weights[1:] * hi).sum())

    @classmethod
    def from_meta(cls, entry: dict[str, Any], source: str) -> LineCheck:
        named, weights = list(entry.get("features", [])), entry.get("weights", ())
        if named != list(FEATURES) or len(weights) != len(FEATURES):
            raise ConfigError(
                f"{source}: its line check reads {entry.get('features')}; accepted: one fitted on this "
                f"version's features ({', '.join(FEATURES)}), as `rebar train` fits it"
            )
        if entry.get("reading") != READING:
            raise ConfigError(
                f"{source}: its line check was fitted reading the bars with {entry.get('reading')}; "
                f"accepted: one fitted with this version's {READING}, as `rebar train` fits it"
            )
        weights, bias = np.asarray(weights, np.float64), float(entry["bias"])
        return cls(weights, bias, float(entry["floor"]), float(entry["checked_from"]))
