"""Keypoint metrics over the visible crossings of a set of images.

- OKS keypoint AP as pycocotools' ``COCOeval(iouType="keypoints")`` computes it, one keypoint per object, a
  stated sigma and the crossing's square box as the object area.
- Pixel errors: per image a one-to-one Hungarian assignment within a 5 px gate; PCK@k, precision and recall
  at the operating threshold, and the best recall at precision 0.99.

Occluded crossings are not ground truth: a prediction on one is a false positive unless they are passed as
``ignore`` regions (COCO's crowd semantics)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from rebar_data.perception.inference.detector import OPERATING_THRESHOLD
from rebar_data.pipeline import DEFAULT_OKS_SIGMA  # stated by the dataset in info.json

OKS_THRESHOLDS = np.linspace(0.5, 0.95, 10)
RECALL_THRESHOLDS = np.linspace(0.0, 1.0, 101)
GATE_PX = 5.0
PCK_PX = (1.0, 2.0, 5.0)


@dataclass
class Truth:
    """One image's visible crossings (pixels, COCO corner origin) and each one's box side (the OKS scale),
    and the crossings that neither count as found nor make a prediction on them wrong (``ignore_``)."""

    uv: np.ndarray
    box_size_px: np.ndarray
    ignore_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    ignore_box_size_px: np.ndarray = field(default_factory=lambda: np.zeros(0))


def oks_radius_px(sigma: float, box_size_px: float, oks: float = 0.5) -> float:
    """Pixel error at which a keypoint with box side ``box_size_px`` scores ``oks``."""
    return float(np.sqrt(-2.0 * np.log(oks)) * 2.0 * sigma * box_size_px)


def oks_matrix(pred_uv: np.ndarray, gt_uv: np.ndarray, box_size_px: np.ndarray, sigma: float) -> np.ndarray:
    """OKS of every prediction (rows) against every ground-truth keypoint (columns), as COCOeval has it."""
    pred_uv = np.asarray(pred_uv, float).reshape(-1, 2)
    gt_uv = np.asarray(gt_uv, float).reshape(-1, 2)
    area = np.asarray(box_size_px, float).reshape(-1) ** 2
    d2 = ((pred_uv[:, None, :] - gt_uv[None, :, :]) ** 2).sum(-1)
    return np.exp(-d2 / (2.0 * sigma) ** 2 / (area[None, :] + np.spacing(1)) / 2.0)


def _match_image(
    oks: np.ndarray, gt_ignore: np.ndarray, thresholds: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """COCOeval.evaluateImg for one image, predictions sorted by score and the ignored ground truth last:
    (matched, ignored) flags of shape (thresholds, predictions)."""
    n_dt, n_gt = oks.shape
    n_real = int((~gt_ignore).sum())  # the ignored ones come last
    matched = np.zeros((len(thresholds), n_dt), bool)
    ignored = np.zeros((len(thresholds), n_dt), bool)
    for ti, t in enumerate(thresholds):
        floor = min(t, 1 - 1e-10)
        taken = np.zeros(n_real, bool)
        for d in range(n_dt):
            # COCOeval walks the ground truth in order and keeps the last one with the highest OKS at or
            # above the threshold, preferring any real match to an ignored one; ignored ones match many
            real = np.where(taken, -np.inf, oks[d, :n_real])
            if n_real and real.max() >= floor:
                m = n_real - 1 - int(np.argmax(real[::-1]))
                taken[m] = True
                matched[ti, d] = True
                continue
            crowd = oks[d, n_real:]
            if len(crowd) and crowd.max() >= floor:
                matched[ti, d] = True
                ignored[ti, d] = True
    return matched, ignored


@dataclass
class APResult:
    """OKS keypoint AP (the mean 101-point interpolated precision over OKS 0.50:0.05:0.95; at 0.5; at 0.75),
    its (thresholds, 101) precision curves, the recall with every prediction per threshold, the sigma."""

    ap: float
    ap50: float
    ap75: float
    precision: np.ndarray
    recall: np.ndarray
    sigma: float


def keypoint_ap(
    truths: Sequence[Truth],
    predictions: Sequence[np.ndarray],
    *,
    sigma: float = DEFAULT_OKS_SIGMA,
    thresholds: np.ndarray = OKS_THRESHOLDS,
) -> APResult:
    """OKS keypoint AP of per-image (N, 3) u, v, score predictions, equal to COCOeval's for one keypoint and
    the same sigma with every prediction kept (COCO's keypoint maxDets of 20 would cap recall)."""
    if len(truths) != len(predictions):
        raise ValueError(f"{len(truths)} truths but {len(predictions)} prediction arrays")
    scores_all, matched_all, ignored_all = [], [], []
    n_gt = 0
    for truth, pred in zip(truths, predictions, strict=True):
        pred = np.asarray(pred, float).reshape(-1, 3)
        pred = pred[np.argsort(-pred[:, 2], kind="mergesort")]
        gt_uv = np.r_[np.reshape(truth.uv, (-1, 2)), np.reshape(truth.ignore_uv, (-1, 2))].astype(float)
        gt_box = np.r_[np.ravel(truth.box_size_px), np.ravel(truth.ignore_box_size_px)].astype(float)
        gt_ignore = np.r_[np.zeros(len(truth.uv), bool), np.ones(len(truth.ignore_uv), bool)]
        n_gt += len(truth.uv)
        if len(pred) == 0:
            continue
        oks = oks_matrix(pred[:, :2], gt_uv, gt_box, sigma)
        matched, ignored = _match_image(oks, gt_ignore, thresholds)
        scores_all.append(pred[:, 2])
        matched_all.append(matched)
        ignored_all.append(ignored)
    precision = np.zeros((len(thresholds), len(RECALL_THRESHOLDS)))
    recall = np.zeros(len(thresholds))
    nan = float("nan")
    if n_gt == 0:
        return APResult(nan, nan, nan, np.full_like(precision, np.nan), np.full_like(recall, np.nan), sigma)
    if scores_all:
        scores = np.concatenate(scores_all)
        order = np.argsort(-scores, kind="mergesort")
        matched = np.concatenate(matched_all, axis=1)[:, order]
        ignored = np.concatenate(ignored_all, axis=1)[:, order]
        tp = np.cumsum(matched & ~ignored, axis=1).astype(float)
        fp = np.cumsum(~matched & ~ignored, axis=1).astype(float)
        for ti in range(len(thresholds)):
            rc = tp[ti] / n_gt
            pr = tp[ti] / (tp[ti] + fp[ti] + np.spacing(1))
            recall[ti] = rc[-1] if len(rc) else 0.0
            pr = np.maximum.accumulate(pr[::-1])[::-1]  # precision made monotonic, as COCOeval does
            idx = np.searchsorted(rc, RECALL_THRESHOLDS, side="left")
            ok = idx < len(pr)
            precision[ti, ok] = pr[idx[ok]]
    per_t = precision.mean(axis=1)
    at = {round(float(t), 2): float(per_t[i]) for i, t in enumerate(thresholds)}
    return APResult(float(per_t.mean()), at.get(0.5, nan), at.get(0.75, nan), precision, recall, sigma)


@dataclass
class PixelResult:
    """Pixel-error metrics at a Hungarian gate: PCK at each of ``PCK_PX`` (the share of visible crossings
    matched within k px by a prediction scoring at least the threshold), those matches' mean and median
    error, precision and recall at the threshold, the best recall while precision >= 0.99, the precision
    and recall along the score-sorted predictions with their scores, and every match's error."""

    n_gt: int
    pck: dict[float, float]
    mean_px: float
    median_px: float
    precision: float
    recall: float
    recall_at_p99: float
    threshold: float
    curve_precision: np.ndarray
    curve_recall: np.ndarray
    curve_score: np.ndarray
    errors_px: np.ndarray


def score_curve(
    scores: np.ndarray, hits: np.ndarray, n_gt: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Detections sorted by score, best first (stable): their scores, hits, and the precision and recall
    after each of them, given ``n_gt`` crossings."""
    order = np.argsort(-scores, kind="mergesort")
    s, h = scores[order], hits[order]
    tps = np.cumsum(h)
    return s, h, tps / np.arange(1, len(s) + 1), tps / max(n_gt, 1)


def recall_at_precision(precision: np.ndarray, recall: np.ndarray, at_least: float = 0.99) -> float:
    """The best recall along a :func:`score_curve` while precision stays at least ``at_least``; 0 if never."""
    ok = precision >= at_least
    return float(recall[ok].max()) if ok.any() else 0.0


def match(gt: np.ndarray, pred: np.ndarray, gate_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-to-one matches within the gate: (pred index, gt index, distance)."""
    if len(gt) == 0 or len(pred) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    d = np.hypot(gt[:, None, 0] - pred[None, :, 0], gt[:, None, 1] - pred[None, :, 1])
    r, c = linear_sum_assignment(np.where(d < gate_px, d, 1e6))
    ok = d[r, c] < gate_px
    return c[ok], r[ok], d[r, c][ok]


def pixel_metrics(
    truths: Sequence[Truth],
    predictions: Sequence[np.ndarray],
    *,
    threshold: float = OPERATING_THRESHOLD,
    gate_px: float = GATE_PX,
) -> PixelResult:
    """PCK, pixel errors, precision and recall of per-image (N, 3) u, v, score predictions, each matched
    (Hungarian) within ``gate_px`` at any score; one matched to an ``ignore`` crossing is not counted."""
    n_gt = 0
    scores, hits, errors = [], [], []
    for truth, pred in zip(truths, predictions, strict=True):
        pred = np.asarray(pred, float).reshape(-1, 3)
        gt = np.asarray(truth.uv, float).reshape(-1, 2)
        n_gt += len(gt)
        both = np.r_[gt, np.asarray(truth.ignore_uv, float).reshape(-1, 2)]
        p_idx, g_idx, dist = match(both, pred[:, :2], gate_px)
        hit, drop = np.zeros(len(pred), bool), np.zeros(len(pred), bool)
        real = g_idx < len(gt)
        hit[p_idx[real]] = True
        drop[p_idx[~real]] = True
        keep = pred[p_idx[real], 2] >= threshold
        errors.append(dist[real][keep])
        scores.append(pred[~drop, 2])
        hits.append(hit[~drop])
    s = np.concatenate(scores) if scores else np.zeros(0)
    h = np.concatenate(hits) if hits else np.zeros(0, bool)
    e = np.concatenate(errors) if errors else np.zeros(0)
    s, h, prec, rec = score_curve(s, h, n_gt)
    above = s >= threshold
    n_above, tp_above = int(above.sum()), int(h[above].sum())
    return PixelResult(
        n_gt=n_gt,
        pck={k: float((e <= k).sum() / max(n_gt, 1)) for k in PCK_PX},
        mean_px=float(e.mean()) if len(e) else float("nan"),
        median_px=float(np.median(e)) if len(e) else float("nan"),
        precision=tp_above / n_above if n_above else float("nan"),
        recall=tp_above / max(n_gt, 1),
        recall_at_p99=recall_at_precision(prec, rec),
        threshold=threshold,
        curve_precision=prec,
        curve_recall=rec,
        curve_score=s,
        errors_px=e,
    )


def ap_ceiling(recall: float) -> float:
    """The most a 101-point interpolated AP can be when every prediction together reaches ``recall``: COCOeval
    counts precision 0 at each recall threshold above it."""
    if not np.isfinite(recall):  # no crossings to find
        return float("nan")
    reached = np.count_nonzero(recall >= RECALL_THRESHOLDS)  # as COCOeval compares
    return float(reached) / len(RECALL_THRESHOLDS)


def summary(
    truths: Sequence[Truth],
    predictions: Sequence[np.ndarray],
    *,
    sigma: float = DEFAULT_OKS_SIGMA,
    threshold: float = OPERATING_THRESHOLD,
) -> dict[str, float]:
    """Every headline figure in one flat dict (what the per-epoch table and the reports hold)."""
    ap = keypoint_ap(truths, predictions, sigma=sigma)
    px = pixel_metrics(truths, predictions, threshold=threshold)
    at50 = int(np.argmin(np.abs(OKS_THRESHOLDS - 0.5)))
    return {
        "oks_ap50": ap.ap50,
        "oks_ap": ap.ap,
        "oks_ap75": ap.ap75,
        # with every prediction, the crossings found at OKS 0.5; and the most AP@0.5 can be at that recall
        "oks_recall50": float(ap.recall[at50]),
        "oks_ap50_ceiling": ap_ceiling(ap.recall[at50]),
        "pck1": px.pck[1.0],
        "pck2": px.pck[2.0],
        "pck5": px.pck[5.0],
        "mean_px": px.mean_px,
        "median_px": px.median_px,
        "precision": px.precision,
        "recall": px.recall,
        "recall_at_p99": px.recall_at_p99,
        "n_gt": float(px.n_gt),
        "oks_sigma": sigma,
        "threshold": threshold,
    }


def format_summary(m: dict[str, float]) -> str:
    """One line with the headline figures."""
    ceiling = f"; recall at OKS 0.5 {m['oks_recall50']:.4f}, so AP@0.5 at most {m['oks_ap50_ceiling']:.4f}"
    return (
        f"{int(m['n_gt'])} visible crossings: OKS AP@0.5 {m['oks_ap50']:.4f}, AP@0.5:0.95 {m['oks_ap']:.4f} "
        f"(sigma {m['oks_sigma']:g}{ceiling}), PCK@1/2/5px {m['pck1']:.3f}/{m['pck2']:.3f}/{m['pck5']:.3f}, "
        f"error mean {m['mean_px']:.2f} median {m['median_px']:.2f} px, P/R@{m['threshold']:g} "
        f"{m['precision']:.3f}/{m['recall']:.3f}, recall@P0.99 {m['recall_at_p99']:.3f}"
    )
