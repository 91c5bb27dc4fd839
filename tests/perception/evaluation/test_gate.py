"""The detector's regression gate (:mod:`rebar_data.perception.evaluation.gate`): the shipped model scored on the gate set,
which the suite builds once, against the reference figures shipped beside it (``models/gate.json``, written by
:mod:`rebar_data.perception.training.gate_reference`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rebar_data.digest import sha256_file
from rebar_data.perception.evaluation import gate
from rebar_data.perception.evaluation.data import Sample
from rebar_data.perception.inference.detector import SHIPPED_MODEL, Detector
from rebar_data.pipeline import load_pipeline


@pytest.fixture(scope="session")
def gate_set(tmp_path_factory):
    """The gate set, built once for the session by the project's renderer (about 35 s on one worker)."""
    if not SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("EGL_PLATFORM", "surfaceless")
        return gate.build_gate_set(tmp_path_factory.mktemp("gate"))


@pytest.fixture(scope="session")
def reference():
    if not SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    assert gate.GATE_FILE.exists(), (
        f"the shipped model has no {gate.GATE_FILE.name} beside it: write it with "
        "`python -m rebar_data.perception.training.gate_reference` (shipping a model writes it)"
    )
    return gate.read_reference()


@pytest.fixture(scope="session")
def measured(gate_set):
    """The shipped model's gate figures on the session's gate set, per mode."""
    return gate.measure(Detector.load(runtime=gate.RUNTIME), gate_set)


def test_the_reference_is_the_shipped_models_on_this_gate_set(reference):
    assert reference["model"]["sha256"] == sha256_file(SHIPPED_MODEL), (
        f"{gate.GATE_FILE.name} was written for another model: rewrite it with `python -m rebar_data.perception.training.gate_reference`"
    )
    cfg = load_pipeline(gate.GATE_PIPELINE)
    assert (reference["set"]["name"], reference["set"]["version"]) == (cfg.name, cfg.version)
    assert set(reference["modes"]) == set(gate.MODES)
    assert reference["runtime"] == gate.RUNTIME


def test_the_shipped_detector_holds_its_gate_figures(gate_set, reference, measured):
    same_set = gate.set_digest(gate_set) == reference["set"]["digest"]
    found = gate.failures(measured, reference)
    assert not found, (
        "the detector scores under its gate: "
        + "; ".join(found)
        + ("" if same_set else " (this machine rendered the gate set differently from the reference's)")
    )


def test_the_gate_catches_the_detector_without_its_second_stage(gate_set, reference, measured):
    """Without the second stage the crossings are placed by the heatmap network alone, about 0.06 of PCK@2px
    lower: the gate must name PCK@2px in both modes."""
    detector = Detector.load(runtime=gate.RUNTIME)
    detector.refiner = None
    degraded = gate.measure(detector, gate_set)
    found = gate.failures(degraded, reference)
    assert any(line.startswith("rgb pck2 ") for line in found), found
    assert any(line.startswith("rgbd pck2 ") for line in found), found
    for mode in gate.MODES:  # what the margin lets through is less than what was lost
        lost = measured[mode]["pck2"] - degraded[mode]["pck2"]
        assert lost > reference["modes"][mode]["margin"]["pck2"]


def test_the_reference_writes_what_the_gate_reads(gate_set, measured, tmp_path):
    from rebar_data.perception.training.gate_reference import write_reference

    out = write_reference(out=tmp_path / "gate.json", data_root=gate_set.parents[1], replicates=20)
    ref = gate.read_reference(out)
    assert ref["set"]["digest"] == gate.set_digest(gate_set)
    assert ref["set"]["visible_crossings"] == ref["modes"]["rgb"]["summary"]["n_gt"] > 250
    for mode, entry in ref["modes"].items():
        assert entry["figures"] == pytest.approx(measured[mode], abs=1e-12)
        for f in gate.FIGURES:
            assert entry["margin"][f] == pytest.approx(gate.K_SE * entry["se"][f])
            assert entry["floor"][f] == pytest.approx(entry["figures"][f] - entry["margin"][f])
            assert entry["se"][f] > 0
    assert gate.failures(measured, ref) == []
    rows = gate.card_rows(out)
    names = list(rows)
    assert [name.rsplit(", ", 1)[1] for name in names] == ["RGB only", "with depth"]
    assert (
        rows[names[0]] == ref["modes"]["rgb"]["summary"] and rows[names[1]] == ref["modes"]["rgbd"]["summary"]
    )


def _reference_of(figures: dict[str, float], margin: float) -> dict:
    entry = {
        "figures": figures,
        "margin": {f: margin for f in figures},
        "floor": {f: v - margin for f, v in figures.items()},
    }
    return {"margin_rule": {"k_se": gate.K_SE}, "modes": {"rgb": entry}}


def test_failures_name_each_figure_under_its_floor_and_no_other():
    ref = _reference_of({"oks_ap50": 0.98, "pck2": 0.95, "recall_at_p99": 0.96}, 0.02)
    assert gate.failures({"rgb": {"oks_ap50": 0.96, "pck2": 0.93, "recall_at_p99": 0.94}}, ref) == []
    found = gate.failures({"rgb": {"oks_ap50": 0.99, "pck2": 0.9299, "recall_at_p99": math.nan}}, ref)
    assert [line.split()[:2] for line in found] == [["rgb", "pck2"], ["rgb", "recall_at_p99"]]


def _one_crossing_images(found: np.ndarray) -> tuple[list[Sample], list[np.ndarray]]:
    """One visible crossing an image; a detection 1 px from it where ``found``, none elsewhere."""
    samples, preds = [], []
    for k, hit in enumerate(found):
        uv = np.array([[50.0, 50.0]])
        samples.append(Sample(f"i{k}", gate.GATE_FILE, 100, 100, uv, np.array([25.0])))
        preds.append(np.array([[51.0, 50.0, 0.9]]) if hit else np.zeros((0, 3)))
    return samples, preds


def test_the_bootstrap_gives_the_binomial_standard_error_and_resamples_whole_groups():
    """With independent images of one crossing each, found with probability p, PCK@2px and recall@P0.99 are
    binomial shares: SE = sqrt(p (1 - p) / n). Grouped four identical images to a group, the SE is that of
    n / 4 draws: twice as large."""
    n, p = 100, 0.8
    found = np.arange(n) < p * n
    samples, preds = _one_crossing_images(found)
    binomial = math.sqrt(p * (1 - p) / n)
    se = gate.bootstrap_se(samples, preds, [str(k) for k in range(n)], sigma=0.04, replicates=200)
    assert se["pck2"] == pytest.approx(binomial, rel=0.15)
    assert se["recall_at_p99"] == pytest.approx(binomial, rel=0.15)
    assert se["oks_ap50"] == pytest.approx(
        binomial, rel=0.15
    )  # no false detection: AP@0.5 is the share found
    grouped = np.repeat(np.arange(n // 4) < p * n // 4, 4)
    samples, preds = _one_crossing_images(grouped)
    se = gate.bootstrap_se(samples, preds, [str(k // 4) for k in range(n)], sigma=0.04, replicates=200)
    assert se["pck2"] == pytest.approx(2 * binomial, rel=0.15)
