"""The shipping steps ``operating point`` and ``line check`` (:mod:`.ship`): the score bias that puts score
0.5 at the best F1 on the validation split, and the line check fitted there."""

from __future__ import annotations

from typing import Any

from rebar_data.perception.evaluation.evaluate import CALIBRATION_FLOOR, calibrate_score_bias, predict
from rebar_data.perception.inference.checks import LineCheck
from rebar_data.perception.inference.detector import Detector, score_bias_of
from rebar_data.perception.training.init import SCORING_STAGES
from rebar_data.perception.training.line_check import UnfitLineCheck, fit_line_check, fitted_on
from rebar_data.perception.training.run import TrainRun
from rebar_data.resume import key_of


def place_operating_point(run: TrainRun, detector: Detector, meta: dict[str, Any], model_key: str) -> None:
    """Place the score bias (score 0.5 = best F1 on val, from the RGB stages' raw scores: depth only lowers)
    and fit the line check on val, each a step; from an init model whose first and second stage are both
    kept, the model's own are kept."""
    cfg, val = run.cfg, run.val
    if run.init is not None and not any(run.trains(s) for s in SCORING_STAGES):
        meta["score_bias"] = detector.score_bias = score_bias_of(run.init.meta)  # as the run time reads it
        if "line_check" in run.init.meta:
            meta["line_check"] = run.init.meta["line_check"]
        detector.line_check = (
            LineCheck.from_meta(meta["line_check"], "the init model") if meta.get("line_check") else None
        )
        run.log("operating point and line check kept: the init model's (its first and second stage are kept)")
        return
    if not val:
        return
    ids = [s.image_id for s in val]

    def bias() -> float:
        raw = predict(detector, val, threshold=CALIBRATION_FLOOR, depth=False, progress=run.progress)
        return calibrate_score_bias(val, raw)

    meta["score_bias"] = detector.score_bias = run.steps.run("operating point", key_of(model_key, ids), bias)
    run.log(f"score bias {meta['score_bias']:+.3f} (score 0.5 = best F1 on val)")
    if not cfg.line_check.enabled:
        return
    data = fitted_on(run.dataset.get("name"), run.line_supplements)

    def line_check() -> dict[str, Any] | None:
        try:
            entry, _ = fit_line_check(
                detector, val + run.line_extra, val, cfg.line_check, data=data, progress=run.progress
            )
        except UnfitLineCheck as e:  # a run too small to have false detections: the model goes without
            run.log(f"no line check: {e}")
            return None
        run.log(f"line check fitted on {entry['candidates']} candidates of {entry['images']} images")
        return entry

    settings = cfg.line_check.model_dump(mode="json")
    key = key_of(model_key, meta["score_bias"], ids, settings, data, [s.image_id for s in run.line_extra])
    entry = run.steps.run("line check", key, line_check)
    if entry is not None:
        meta["line_check"] = entry
        detector.line_check = LineCheck.from_meta(entry, str(run.out / "best.onnx"))
