"""Fitting the line check (:mod:`rebar_data.perception.inference.checks`) to a trained detector.

The detector, without depth and line check, reads each fitting image as the check would
(``Detector.line_pass``); a checked candidate within the scorer's gate of a visible crossing (matched
one-to-one) is a positive, one matched to an ignored crossing is left out, every other a negative. A
logistic regression is fitted on their features, and its bias moved so that score 0.5 is the best F1 on
the validation images."""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import Sample, read_sample_image
from rebar_data.perception.evaluation.evaluate import calibrate_score_bias, predict, truth_of
from rebar_data.perception.evaluation.metrics import GATE_PX, match
from rebar_data.perception.inference.checks import FEATURES, READING, LineCheck, line_features
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.training.config import LineCheckConfig


class UnfitLineCheck(ConfigError):
    """The fitting images give the line check nothing to learn from: no candidates, or only one kind."""


def line_check_meta(check: LineCheck) -> dict[str, Any]:
    """A fitted check's entry in the model file's meta, as :meth:`LineCheck.from_meta` reads it."""
    return {
        "features": list(FEATURES),
        "weights": [float(w) for w in check.weights],
        "bias": float(check.bias),
        "floor": check.floor,
        "checked_from": check.checked_from,
        "reading": dict(READING),
    }


def fitting_rows(
    detector: Detector, samples: Sequence[Sample], cfg: LineCheckConfig, *, progress: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """The line check's features (M, F) of every candidate the detector checks in ``samples``
    (``Detector.line_pass``), and whether each is a crossing (M,)."""
    xs, ys = [], []
    for k, s in enumerate(samples):
        rgb = read_sample_image(s)
        seen = detector.line_pass(rgb, detector.raw(rgb, camera=s.camera), cfg.floor, cfg.checked_from)
        if not len(seen.checked):
            continue
        truth = truth_of(s)
        gt = np.asarray(truth.uv, float).reshape(-1, 2)
        both = np.r_[gt, np.asarray(truth.ignore_uv, float).reshape(-1, 2)]
        p_idx, g_idx, _ = match(both, seen.placed, GATE_PX)
        label = np.zeros(len(seen.checked), int)
        label[p_idx] = np.where(g_idx < len(gt), 1, -1)  # -1: an ignored crossing, left out
        x = line_features(rgb, seen.uv, seen.evidence, seen.checked)
        xs.append(x[label >= 0])
        ys.append(label[label >= 0])
        if progress and (k + 1) % 50 == 0:
            print(f"line check: {k + 1}/{len(samples)} images read", file=sys.stderr)
    if not xs:
        raise UnfitLineCheck("the line check found no candidates to fit on; accepted: images with crossings")
    return np.concatenate(xs), np.concatenate(ys)


def fitted_on(dataset: str | None, supplements: Sequence[dict[str, Any]]) -> list[str]:
    """What a check's metadata says it was fitted on: ``dataset``'s val split and each supplement
    (:func:`~rebar_data.perception.training.train.supplement_images`' records)."""
    return [f"{dataset} val"] + [f"{m['name']} v{m['version']}" for m in supplements]


def fit_line_check(
    detector: Detector,
    samples: Sequence[Sample],
    val_samples: Sequence[Sample],
    cfg: LineCheckConfig,
    *,
    data: Sequence[str] = (),
    progress: bool = False,
) -> tuple[dict[str, Any], LineCheck]:
    """The line check fitted on the candidates of ``samples`` (the validation images among them or not), its
    operating point set on ``val_samples``, and its model-file entry (``data``: the fitting datasets)."""
    from sklearn.linear_model import LogisticRegression

    t0 = time.perf_counter()
    x, y = fitting_rows(detector, samples, cfg, progress=progress)
    if len(np.unique(y)) < 2:
        raise UnfitLineCheck(
            "the line check needs both crossings and false detections to fit on; accepted: fitting images "
            "where the detector finds some of each (the validation split and the Cycles supplements)"
        )
    reg = LogisticRegression(C=cfg.regularization, max_iter=5000).fit(x, y)
    check = LineCheck(reg.coef_[0].astype(np.float64), float(reg.intercept_[0]), cfg.floor, cfg.checked_from)
    shift = 0.0
    if val_samples:
        before, detector.line_check = detector.line_check, check
        try:
            preds = predict(detector, val_samples, threshold=cfg.floor, depth=False)
            shift = calibrate_score_bias(list(val_samples), preds)
        finally:
            detector.line_check = before
        check = LineCheck(check.weights, check.bias + shift, cfg.floor, cfg.checked_from)
    entry = {
        **line_check_meta(check),
        "regularization": cfg.regularization,
        "fitted_on": list(data),
        "images": len(samples),
        "candidates": int(len(y)),
        "crossings": int(y.sum()),
        "bias_shift": shift,
        "seconds": time.perf_counter() - t0,
    }
    return entry, check
