"""Where a detector's confident false detections (unmatched within the metrics' 5 px gate) lie: those scoring
above the score at which recall reaches ``RECALL``, each put in the first place it lies in:
``top_over_lower`` (where a top bar passes in front of a lower bar), ``lower_mat`` (a lower-mat crossing),
``border`` (within ``BORDER_PX`` of the edge), ``beside_crossing`` (within ``BESIDE_PX`` of a visible
crossing) or ``elsewhere``."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from rebar_data.perception.evaluation.data import Sample
from rebar_data.perception.evaluation.lower_mat import lower_mat_places
from rebar_data.perception.evaluation.metrics import GATE_PX, match, recall_at_precision, score_curve

PLACES = ("top_over_lower", "lower_mat", "border", "beside_crossing", "elsewhere")
NEAR_PX = 6.0  # a false detection this close to a lower-mat place is counted there
BORDER_PX = 12.0
BESIDE_PX = 12.0
RECALL = 0.97


def _distance(uv: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Each of ``uv`` (N, 2)'s distance to the nearest of ``points`` (M, 2); inf when there are none."""
    if not len(uv) or not len(points):
        return np.full(len(uv), np.inf)
    return np.linalg.norm(uv[:, None] - points[None], axis=2).min(axis=1)


def _place_of(s: Sample, uv: np.ndarray, placed: dict[str, np.ndarray]) -> np.ndarray:
    """The index in ``PLACES`` of each false detection at ``uv`` (N, 2): the first place it lies in."""
    edge = np.minimum.reduce([uv[:, 0], uv[:, 1], s.width - uv[:, 0], s.height - uv[:, 1]])
    over, own = _distance(uv, placed["top_over_lower"]), _distance(uv, placed["own"])
    where = (
        (over <= NEAR_PX) & (over <= own),  # the nearer of the two kinds
        own <= NEAR_PX,
        edge <= BORDER_PX,
        _distance(uv, np.asarray(s.visible, float).reshape(-1, 2)) <= BESIDE_PX,
        np.ones(len(uv), bool),
    )
    return np.argmax(np.stack(where), axis=0) if len(uv) else np.zeros(0, int)


def false_detection_census(
    root: str | Path, samples: Sequence[Sample], predictions: Sequence[np.ndarray], *, recall: float = RECALL
) -> dict:
    """The false detections of ``samples`` of the dataset at ``root`` (whose tables place the lower mat)
    scoring at least the score where recall reaches ``recall``, by place, and what recall at precision 0.99
    would be without each place's false detections, whatever their score. Returns ``recall``, ``reached``
    (False: recall never reaches it, and every prediction counts), ``score`` (the cut), ``false`` and
    ``true`` (the detections above it), one count per place in ``PLACES``, ``recall_at_p99`` and
    ``recall_at_p99_without`` (place -> recall at precision 0.99)."""
    if not 0.0 < recall <= 1.0:
        raise ValueError(f"recall = {recall} is not accepted; accepted: a number in (0, 1]")
    hits, scores, place = [], [], []
    n_gt = 0
    placed_all = lower_mat_places(root, list(samples))
    for s, p, placed in zip(samples, predictions, placed_all, strict=True):
        p = np.asarray(p, float).reshape(-1, 3)
        n_gt += len(s.visible)
        hit = np.zeros(len(p), bool)
        hit[match(np.asarray(s.visible, float).reshape(-1, 2), p[:, :2], GATE_PX)[0]] = True
        at = np.full(len(p), -1)  # -1: a true detection
        at[~hit] = _place_of(s, p[~hit, :2], placed)
        hits.append(hit)
        scores.append(p[:, 2])
        place.append(at)
    s_all = np.concatenate(scores) if scores else np.zeros(0)
    h_all = np.concatenate(hits) if hits else np.zeros(0, bool)
    at_all = np.concatenate(place) if place else np.zeros(0, int)
    s_sorted, h_sorted, precision, recall_curve = score_curve(s_all, h_all, n_gt)
    reached_at = np.nonzero(np.cumsum(h_sorted) >= recall * n_gt)[0] if n_gt else np.zeros(0, int)
    reached = bool(len(reached_at))
    cut = float(s_sorted[reached_at[0]]) if reached else (float(s_all.min()) if len(s_all) else 0.0)
    above = s_all >= cut
    counts = {name: int((above & (at_all == k)).sum()) for k, name in enumerate(PLACES)}
    without = {
        name: recall_at_precision(*score_curve(s_all[at_all != k], h_all[at_all != k], n_gt)[2:])
        for k, name in enumerate(PLACES)
    }
    return {
        "recall": recall,
        "reached": reached,
        "score": cut,
        "false": int(sum(counts.values())),
        "true": int(h_all[above].sum()),
        **counts,
        "recall_at_p99": recall_at_precision(precision, recall_curve),
        "recall_at_p99_without": without,
    }


def format_census(c: dict) -> str:
    """One line: how many false detections score above the recall's cut, where they lie, and the recall at
    precision 0.99 without each place's."""
    where = ", ".join(f"{c[p]} {p.replace('_', ' ')}" for p in PLACES)
    at = f"the score where recall reaches {c['recall']:g} ({c['score']:.3f})"
    if not c["reached"]:
        at = f"every prediction (recall never reaches {c['recall']:g})"
    without = ", ".join(
        f"{v:.3f} without the {p.replace('_', ' ')} ones"
        for p, v in c["recall_at_p99_without"].items()
        if c[p]
    )
    gain = f"; recall at precision 0.99 {c['recall_at_p99']:.3f}, {without}" if without else ""
    return f"{c['false']} false detections above {at}: {where}{gain}"
