"""The line check: each detection's score read again beside the detections along its two bars.

Where a top bar passes in front of a lower mat's bar, the patch looks like a crossing, and from colour
alone the stages before this one cannot tell it from one (on the Cycles sets they are nearly all the
confident false detections). A bar can: a crossing of the top mat lies on two top bars, and along each
the detector finds other crossings, most of them confident; a place where a top bar hides a lower bar
lies on that lower bar, and along it there are only more such places and the lower mat's own crossings,
scored lower on the whole. So each detection is weighed with the scores of the detections along its
two bars.

The candidates are every place the first stage scores :data:`FLOOR` or more inside the frame; each is
evidence for the others with its score (the RGB stages' score, the second stage's verification counted,
for those the first stage scores :data:`CHECKED_FROM` or more; its first-stage score for the rest, sparing
the second stage's patches where no score could reach an operating point). For each of the former:

- its two bar directions are read from the image: the two strongest edge orientations (the gradient's,
  turned a quarter) within :data:`RADIUS_PX`, at least :data:`MIN_APART_DEG` apart;
- each bar is followed from candidate to candidate both ways, up to :data:`STEPS` steps: the nearest
  candidate ahead inside a cone of :data:`CONE_DEG` (plus :data:`LATERAL_PX`) and nearer than
  :data:`MAX_STEP_PX`, the direction then taken from the step just made (a curved tunnel bar is
  followed along its curve, and a lower bar is not confused with the top bar it converges to in
  perspective);
- the scores found along each bar are summarised (:data:`FEATURES`: how many, their mean, upper quartile,
  best, share of 0.8 or more, share above the detection's own, mean of the best two), the better-scored
  bar first;
- a logistic regression on the detection's own score (its logit) and those fourteen figures gives the new
  score (:mod:`rebar_data.perception.training.line_check` fits it).

It needs no network and no depth; with a depth image the depth check tells the places apart better, and
the detector leaves this check out (``Detector.detect``). Measured: see ``LineCheckConfig``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import cv2
import numpy as np

from rebar_data.errors import ConfigError

# defaults of LineCheckConfig.floor and .checked_from (a fitted check carries its own in the model file)
FLOOR = 0.05  # candidates the first stage scores below this are not followed, nor checked
CHECKED_FROM = 0.3  # ... those it scores this or more are verified by the second stage and checked
RADIUS_PX = 40  # the bar directions are read within this many pixels of a candidate
BINS = 60  # edge orientations, 3 degrees a bin over 180
MIN_APART_DEG = 25.0  # the second bar direction is this far from the first at least
CONE_DEG = 4.0
LATERAL_PX = 2.0
MAX_STEP_PX = 260.0
MIN_STEP_PX = 5.0
STEPS = 6  # along each bar, each way
HIGH = 0.8
_SUMMARY = ("count", "mean", "upper_quartile", "best", "share_high", "share_above_own", "best_two")
FEATURES = ("own_logit", *(f"{bar}_{s}" for bar in ("better_bar", "other_bar") for s in _SUMMARY))
_LOGIT_CLIP = 1e-3
# what a fitted check's weights depend on beyond its features' names: a file fitted with others is refused
READING = {
    "radius_px": RADIUS_PX,
    "bins": BINS,
    "min_apart_deg": MIN_APART_DEG,
    "cone_deg": CONE_DEG,
    "lateral_px": LATERAL_PX,
    "max_step_px": MAX_STEP_PX,
    "min_step_px": MIN_STEP_PX,
    "steps": STEPS,
    "high": HIGH,
}
_TAN = float(np.tan(np.deg2rad(CONE_DEG)))
_MODULO = (np.arange(256) % BINS).astype(np.uint8)  # orientation bins past 180 degrees folded back
_EVERY_OTHER = np.arange(0, RADIUS_PX, 2)  # the pixels of a half-resolution window read, along each side


def logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(np.asarray(p, np.float64), _LOGIT_CLIP, 1 - _LOGIT_CLIP)
    return np.log(p / (1 - p))


def bar_directions(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N, 2) angles in radians (image axes, v down) of the two bars crossing at each of ``uv`` (N, 2), the
    stronger first: the peaks of the gradient's orientation histogram (magnitude-weighted, smoothed over
    five bins) in the square reaching :data:`RADIUS_PX` around each point, read at half resolution."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if not len(uv):
        return np.zeros((0, 2))
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    # at half resolution (the thinnest bars are 5 px wide at full): a quarter of the pixels to read
    gray = cv2.resize(gray, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA).astype(np.float32)
    h, w = gray.shape
    mag, ang = cv2.cartToPolar(
        cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3),
        cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3),
        angleInDegrees=True,
    )
    # the nearest of BINS orientations (modulo 180 degrees); bin k is k * 180 / BINS degrees
    bins = cv2.LUT(cv2.convertScaleAbs(ang, alpha=BINS / 180.0), _MODULO)
    r = RADIUS_PX // 2
    bins = cv2.copyMakeBorder(bins, r, r, r, r, cv2.BORDER_CONSTANT, value=0)
    mag = cv2.copyMakeBorder(mag, r, r, r, r, cv2.BORDER_CONSTANT, value=0.0)  # beyond the image: no edges
    # each window's corner in the bordered images is its centre's pixel at half resolution; a point off
    # the image reads the window of the nearest point on it
    centre = np.floor(uv / 2).astype(np.int64)
    top = np.clip(centre[:, 1], 0, h)
    left = np.clip(centre[:, 0], 0, w)
    # every other pixel of each window: as good a histogram, a quarter of the sums (gathered alone: cutting
    # whole windows and then every other pixel of them read four times the memory, 0.9 against 0.6 ms)
    rows = (top[:, None] + _EVERY_OTHER)[:, :, None]
    cols = (left[:, None] + _EVERY_OTHER)[:, None, :]
    b = bins[rows, cols].astype(np.int64) + BINS * np.arange(len(uv))[:, None, None]
    hist = np.bincount(b.ravel(), mag[rows, cols].ravel(), len(uv) * BINS).reshape(len(uv), BINS)
    # smoothed over five bins, weights 1 2 3 2 1, around the circle of orientations (summed in this order)
    ring = np.concatenate([hist[:, -2:], hist, hist[:, :2]], axis=1)  # ring[:, i + 2] is hist[:, i]
    hist = ring[:, 4:] + 2 * ring[:, 3:-1] + 3 * ring[:, 2:-2] + 2 * ring[:, 1:-3] + ring[:, :-4]
    first = np.argmax(hist, axis=1)
    apart = np.abs((np.arange(BINS)[None, :] - first[:, None] + BINS / 2) % BINS - BINS / 2)
    second = np.argmax(np.where(apart >= BINS * MIN_APART_DEG / 180.0, hist, -1.0), axis=1)
    normals = np.stack([first, second], axis=1) * (np.pi / BINS)
    return normals + np.pi / 2  # a bar runs across its edges' gradient


def bar_members(uv: np.ndarray, directions: np.ndarray, which: np.ndarray | None = None) -> np.ndarray:
    """(K, 2, 2 * STEPS) the candidates ``uv`` (N, 2) met following the two bars of each candidate ``which``
    names (K indices; None: all) both ways, -1 past a bar's last one; ``directions`` (K, 2) are the bars'
    angles, row for row with ``which``."""
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
    """(K, len(FEATURES)) what the line check reads for each candidate ``which`` names (None: all): its own
    score's logit and the summaries of the scores (``score``, every candidate's) along its two bars
    (``members``, row for row with ``which``, from :func:`bar_members`), better bar first."""
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
    """(K, len(FEATURES)) what the check reads for the candidates ``which`` (K indices) among an image's
    candidates ``uv`` (N, 2) scored ``evidence`` (N,): their bars read from ``image`` and followed."""
    return features(evidence, bar_members(uv, bar_directions(image, uv[which]), which), which)


@dataclass(frozen=True)
class LineCheck:
    """A fitted line check: ``weights`` (one per :data:`FEATURES`) and ``bias`` of its logistic regression,
    and the first-stage scores it was fitted with: ``floor`` (candidates) and ``checked_from`` (verified and
    checked)."""

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
        """(K,) the new scores of the candidates ``checked`` (K indices) names among an image's candidates
        ``uv`` (N, 2), each scored ``evidence`` (N,) (see ``Detector.line_inputs``). A candidate the check
        could not lift to ``threshold`` whatever its bars show scores 0 (its bars are not followed)."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        evidence = np.asarray(evidence, np.float64)
        checked = np.asarray(checked, np.int64)
        out = np.zeros(len(checked))
        reach = self.best_logit(evidence[checked]) >= np.log(threshold / (1 - threshold))
        which = checked[reach]
        if len(which):
            x = line_features(image, uv, evidence, which)
            out[reach] = 1.0 / (1.0 + np.exp(-(x @ self.weights + self.bias)))
        return out

    def best_logit(self, score: np.ndarray) -> np.ndarray:
        """(N,) the highest logit the check can give a candidate scored ``score``, whatever its bars show."""
        w = self.weights[0]
        own = logit(score)
        if w < 0:  # a lower own score would do better: bound by the lowest own logit
            own = np.full(len(own), logit(np.array([0.0]))[0])
        return w * own + self._most_from_bars + self.bias

    @cached_property
    def _most_from_bars(self) -> float:
        """The most the bar summaries can add to the logit: each lies between 0 and 1, a count between 0
        and twice :data:`STEPS`."""
        hi = np.ones(len(FEATURES) - 1)
        hi[[FEATURES.index(f"{bar}_count") - 1 for bar in ("better_bar", "other_bar")]] = 2 * STEPS
        return float(np.maximum(0.0, self.weights[1:] * hi).sum())

    def to_meta(self) -> dict[str, Any]:
        return {
            "features": list(FEATURES),
            "weights": [float(w) for w in self.weights],
            "bias": float(self.bias),
            "floor": self.floor,
            "checked_from": self.checked_from,
            "reading": dict(READING),
        }

    @classmethod
    def from_meta(cls, entry: dict[str, Any], source: str) -> LineCheck:
        if list(entry.get("features", [])) != list(FEATURES) or len(entry.get("weights", [])) != len(
            FEATURES
        ):
            raise ConfigError(
                f"{source}: its line check reads {entry.get('features')}; accepted: one fitted on this "
                f"version's features ({', '.join(FEATURES)}), as `rebar train` fits it"
            )
        if entry.get("reading") != READING:
            raise ConfigError(
                f"{source}: its line check was fitted reading the bars with {entry.get('reading')}; accepted: "
                f"one fitted with this version's {READING}, as `rebar train` fits it"
            )
        return cls(
            np.asarray(entry["weights"], np.float64),
            float(entry["bias"]),
            float(entry["floor"]),
            float(entry["checked_from"]),
        )
