from __future__ import annotations

import numpy as np

from rebar_data.perception.evaluation.bench import detector_latency, drawn_frame, flatten_cost
from rebar_data.perception.inference.detector import Detector


def test_latency_counts_the_later_stages_candidates_apart_from_what_they_keep(trained_run):
    det = Detector.load(trained_run.out_dir, threads=1)
    assert det.refiner is not None
    assert det.depth_check is not None
    rgb, depth = drawn_frame()
    frames = [(rgb, depth), (rgb[:, ::-1].copy(), depth[:, ::-1].copy())]
    lat = detector_latency(det, frames, repeats=6)
    with det.first_stage_only():
        candidates = np.mean([len(det.detect(c, depth=d)) for c, d in frames])
    kept = np.mean([len(det.detect(c, depth=d)) for c, d in frames])  # the depth check counts too
    assert lat.frames == 2 and lat.candidates == candidates and lat.crossings == kept
    assert lat.first_stage_ms is not None and lat.second_stage_us_per_candidate is not None
    assert lat.p90_ms >= lat.median_ms > 0


def test_a_one_stage_detector_has_no_second_stage_figure(trained_run):
    det = Detector.load(trained_run.out_dir, threads=1)
    det.refiner = det.depth_check = None
    lat = detector_latency(det, [drawn_frame()], repeats=3)
    assert lat.first_stage_ms is None and lat.second_stage_us_per_candidate is None
    assert lat.candidates == lat.crossings


def test_flattening_is_timed_on_and_off_and_the_detector_left_as_it_was(trained_run, monkeypatch):
    from rebar_data.perception.inference import detector as infer

    det = Detector.load(trained_run.out_dir, threads=1)
    rgb, depth = drawn_frame()
    calls = []
    monkeypatch.setattr(infer, "flatten_behind", lambda image, depth_m: calls.append(1) or image)
    on_ms, off_ms = flatten_cost(det, [(rgb, depth)], repeats=3)
    assert on_ms > 0 and off_ms > 0
    assert len(calls) == 3 + 3  # three timed calls with it, each after one warm-up call; none without
    assert det.flatten_behind is False
