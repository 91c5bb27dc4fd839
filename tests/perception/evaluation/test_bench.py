from __future__ import annotations

import numpy as np

from rebar_data.perception.evaluation.bench import detector_latency
from rebar_data.perception.evaluation.evaluate import first_stage_only
from rebar_data.perception.inference.detector import Detector
from tests.perception.synthetic import drawn_frame


def test_latency_counts_the_later_stages_candidates_apart_from_what_they_keep(trained_run):
    det = Detector.load(trained_run.out_dir, threads=1)
    assert det.refiner is not None
    assert det.depth_check is not None
    rgb, depth = drawn_frame()
    frames = [(rgb, depth), (rgb[:, ::-1].copy(), depth[:, ::-1].copy())]
    lat = detector_latency(det, frames, repeats=6)
    with first_stage_only(det):
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
