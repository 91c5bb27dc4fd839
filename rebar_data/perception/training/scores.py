"""The shipping step ``scores`` (:mod:`.ship`): the figures a run's model is shipped with, on its validation
and test splits."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from rebar_data.perception.evaluation.evaluate import at_crossing_points, first_stage_only, predict, score
from rebar_data.perception.evaluation.metrics import format_summary
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.training.run import TrainRun
from rebar_data.resume import key_of


def score_model(run: TrainRun, detector: Detector, model_key: str) -> dict[str, Any]:
    """The shipped detector's figures (a step): each split, the first stage alone and the test split
    without depth and against the 3D crossing points."""
    sigma, val_samples, test_samples = run.sigma, run.val, run.test

    def compute() -> dict[str, Any]:
        results: dict[str, dict[str, float]] = {}
        for split, samples in (("val", val_samples), ("test", test_samples)):
            if samples:
                results[split] = score(
                    samples, predict(detector, samples, progress=run.progress), sigma=sigma
                )
        first_stage: dict[str, dict[str, float]] = {}
        if detector.refiner is not None and test_samples:  # what the second stage adds, on the reported split
            with first_stage_only(detector):
                first_stage["test"] = score(test_samples, predict(detector, test_samples), sigma=sigma)
        without_depth: dict[str, dict[str, float]] = {}
        against_points: dict[str, dict[str, float]] = {}
        wanted = (detector.depth_check is not None, detector.crossing_point is not None)
        rgb_only = predict(detector, test_samples, depth=False) if test_samples and any(wanted) else []
        if detector.depth_check is not None and test_samples:  # what the depth check adds
            without_depth["test"] = score(test_samples, rgb_only, sigma=sigma)
        if detector.crossing_point is not None and test_samples and test_samples[0].crossings is not None:
            # the 3D crossing points as truth, found from RGB alone: the sight points and the stage's output
            points = [replace(s, visible=s.crossings) for s in test_samples]
            found = {
                "sight points": rgb_only,
                "crossing points": at_crossing_points(detector, test_samples, rgb_only),
            }
            against_points = {name: score(points, preds, sigma=sigma) for name, preds in found.items()}
        return {
            "results": results,
            "first_stage": first_stage,
            "without_depth": without_depth,
            "points": against_points,
        }

    ids = [[s.image_id for s in val_samples], [s.image_id for s in test_samples]]
    found = run.steps.run("scores", key_of(model_key, ids, sigma), compute)
    for split, m in found["results"].items():
        run.log(f"the model on {split}: {format_summary(m)}")
    for name, m in (
        ("first stage alone", found["first_stage"].get("test")),
        ("without the depth check", found["without_depth"].get("test")),
    ):
        if m:
            run.log(f"{name} on test: {format_summary(m)}")
    for name, m in found["points"].items():
        run.log(f"against the 3D crossing points on test, RGB only, {name}: {format_summary(m)}")
    return found
