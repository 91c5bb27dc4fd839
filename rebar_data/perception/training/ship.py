"""Shipping a trained model: one pipeline of named steps.

Finishing a run, in its folder (:func:`finish`, the end of ``rebar train``):

- ``export``: the first stage (best or adapted) and the later stages as ONNX files (:mod:`.export`);
- ``int8 copy``: the second stage's int8 copy for its later passes (:func:`.export.int8_copy`);
- ``operating point`` and ``line check``: placed and fitted on the validation split (:mod:`.operating_point`);
- ``scores``: the figures of the validation and test splits (:mod:`.scores`);
- ``results``: ``best.onnx`` and ``best.pt`` carrying them, and ``results.json``;
- ``plots``: ``curves.png``, ``pr_curve.png`` and ``predictions.png``.

Shipping it with the package (:func:`ship`, ``rebar train --ship``):

- ``copy``: the run's model files into the package's models folder;
- ``card: <set>``: the card's rows, one step a dataset (:mod:`~rebar_data.perception.evaluation.card_rows`);
- ``gate``: the regression gate's reference beside the model (:mod:`.gate_reference`) and its card rows;
- ``card``: the card's figures and ``MODEL_CARD.md`` (:mod:`.card`).

The steps that take long (the int8 copy, the operating point, the line check, the scores and each dataset's
card rows) are kept in the run folder's ``steps.json`` (:class:`~rebar_data.resume.Steps`): run again after a
kill, a step whose inputs are the same is taken from there."""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rebar_data.config import ConfigError
from rebar_data.digest import sha256_file
from rebar_data.outputs import replace_file
from rebar_data.perception.evaluation import data
from rebar_data.perception.evaluation.bench import detector_latency, latency_frames, runtime_description
from rebar_data.perception.evaluation.card_rows import HeldOut, evaluation_rows
from rebar_data.perception.evaluation.evaluate import predict, truth_of
from rebar_data.perception.evaluation.metrics import OPERATING_THRESHOLD, keypoint_ap, pixel_metrics
from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.detector import MODELS_DIR, SHIPPED_MODEL, Detector
from rebar_data.perception.networks.files import export_onnx, save_checkpoint
from rebar_data.perception.networks.keypoint_net import count_parameters
from rebar_data.perception.training.card import CARD_NAME, write_figures, write_model_card
from rebar_data.perception.training.export import Exported, export_model
from rebar_data.perception.training.operating_point import place_operating_point
from rebar_data.perception.training.run import TrainRun
from rebar_data.perception.training.scores import score_model
from rebar_data.resume import STEPS_FILE, Steps, key_of

MAX_SHIPPED_BYTES = 5 * 1024 * 1024


def finish(
    run: TrainRun, state: dict[str, Any], first_path: Path, stages: dict[str, tuple[Any, list]]
) -> dict[str, dict[str, float]]:
    """The finishing steps on ``first_path`` (best or adapted) and the later ``stages`` (key -> network, None
    when off, and history), after the epochs that ``state`` records; returns the model's metrics per split."""
    exported = export_model(run, first_path, stages)
    detector, meta, model_key = exported.detector, exported.meta, exported.model_key
    place_operating_point(run, detector, meta, model_key)
    found = score_model(run, detector, key_of(model_key, meta.get("score_bias"), meta.get("line_check")))
    write_results(run, state, exported, stages, found)
    draw_plots(run, state, detector)
    return found["results"]


def write_results(
    run: TrainRun,
    state: dict[str, Any],
    exported: Exported,
    stages: dict[str, tuple[Any, list]],
    found: dict[str, Any],
) -> None:
    """The step ``results``: the first stage's files carrying the score bias and results, and ``results.json``
    (the run's epochs, times, parameters and every figure ``found``)."""
    out, net, results = run.out, exported.net, found["results"]
    meta = {**exported.meta, "results": results}
    save_checkpoint(exported.first_path, net, meta)
    export_onnx(net, out / "best.onnx", meta)  # the file now carries its score bias and results
    seconds = {k: float(sum(r.get("seconds", 0.0) for r in history)) for k, (_, history) in stages.items()}
    summary_doc = {
        "best_epoch": state["best_epoch"],
        "epochs_run": state["epoch"],
        "stopped_early": state["stopped"],
        "oks_sigma": run.sigma,
        "threshold": OPERATING_THRESHOLD,
        "dataset": run.dataset,
        "parameters": count_parameters(net),
        "train_seconds_this_call": run.train_seconds,
        "train_seconds_total": float(
            sum(r.get("train_seconds", 0.0) for r in state["history"]) + sum(seconds.values())
        ),
        "adapt_epochs": len(stages["adapt"][1]),
        "results": results,
        "results_against_crossing_points": found["points"],
        "results_first_stage": found["first_stage"],
        "results_without_depth": found["without_depth"],
    }
    for key, (stage_net, history) in stages.items():
        if key != "adapt":
            name = "refiner" if key == "refine" else key
            summary_doc[f"{name}_parameters"] = count_parameters(stage_net) if stage_net is not None else 0
        summary_doc[f"{key}_seconds"] = seconds[key]
        summary_doc[f"{key}_history"] = history
    (out / "results.json").write_text(json.dumps(summary_doc, indent=2, sort_keys=True) + "\n")


def draw_plots(run: TrainRun, state: dict[str, Any], detector: Detector) -> None:
    """The step ``plots``: the epochs' curves, and the precision-recall curve and detections of the test split
    (the validation split without one)."""
    from rebar_data.perception.evaluation import plots

    cfg, out, sigma, test_samples = run.cfg, run.out, run.sigma, run.test
    if state["history"]:
        plots.plot_history(state["history"], out / "curves.png", mosaic_epochs=cfg.augment.mosaic_epochs)
    split = "test" if test_samples else ("val" if run.val else None)
    if split:
        samples = test_samples if split == "test" else run.val
        preds = predict(detector, samples, progress=run.progress)
        truths = [truth_of(s) for s in samples]
        curve = (keypoint_ap(truths, preds, sigma=sigma), pixel_metrics(truths, preds))
        title = f"{split} split, OKS sigma {sigma:g}"
        plots.plot_pr_modes({"detections": curve}, out / "pr_curve.png", title=title)
        plots.plot_prediction_grid(samples, preds, out / "predictions.png")


def ship(
    run_dir: str | Path,
    *,
    models_dir: Path = MODELS_DIR,
    evaluate_on: Sequence[str | Path] = (),
    progress: bool = False,
    gate: bool = True,
) -> Path:
    """Copy a finished run's ``best.onnx`` and its later stages into ``models_dir`` as the shipped model and
    write its card and figures, scored also on every split of each dataset in ``evaluate_on``. ``gate``: also
    write the regression gate's reference beside it (``gate.json``; False removes a stale one)."""
    from rebar_data.perception.evaluation.gate import GATE_NAME

    run_dir = Path(run_dir)
    dst = _copy(run_dir, models_dir, evaluate_on)
    detector = Detector.load(dst, runtime="onnxruntime")  # the card's figures: float32, as trained
    held_out: dict[str, HeldOut] = {}
    # each dataset's scoring is a step kept in the run folder: a ship run again after a kill reuses it
    steps = Steps(run_dir / STEPS_FILE, log=(lambda m: print(m, file=sys.stderr)) if progress else None)
    model_key = key_of([sha256_file(f) for f in (dst, *model_file.stage_files(dst)) if f.exists()])
    rows = evaluation_rows(
        detector,
        run_dir,
        evaluate_on=evaluate_on,
        progress=progress,
        held_out=held_out,
        steps=steps,
        model_key=model_key,
    )
    if gate:
        rows |= _gate_rows(detector, dst, models_dir, held_out)
    else:
        (models_dir / GATE_NAME).unlink(missing_ok=True)
    _card(run_dir, models_dir, model=dst, detector=detector, rows=rows, held_out=held_out)
    return dst


def _copy(run_dir: Path, models_dir: Path, evaluate_on: Sequence[str | Path]) -> Path:
    """The step ``copy``: the run's model files into ``models_dir``, once the run, its size and every dataset
    to score on are checked; returns the shipped first stage's file."""
    src = run_dir / "best.onnx"
    if not src.exists() or not (run_dir / "results.json").exists():
        raise ConfigError(
            f"{run_dir}: no best.onnx and results.json; accepted: a finished `rebar train` run folder"
        )
    size = sum(p.stat().st_size for p in (src, *model_file.stage_files(src)) if p.exists())
    if size > MAX_SHIPPED_BYTES:
        raise ConfigError(
            f"{src}: {size / 2**20:.1f} MiB (with its later stages) is over the "
            f"{MAX_SHIPPED_BYTES / 2**20:.0f} MiB a shipped model may take"
        )
    for path in evaluate_on:
        data.check_dataset(path)  # a wrong path fails before anything is copied
    dst = models_dir / SHIPPED_MODEL.name
    files = list(zip([src, *model_file.stage_files(src)], [dst, *model_file.stage_files(dst)], strict=True))
    for a, b in reversed(files):  # the later stages land first, so the first never names a missing file
        if a.exists():
            replace_file(b, lambda tmp, a=a: shutil.copyfile(a, tmp))
        else:
            b.unlink(missing_ok=True)  # a model without that stage: no stale file beside it
    return dst


def _card(
    run_dir: Path,
    models_dir: Path,
    *,
    model: Path,
    detector: Detector,
    rows: dict[str, dict],
    held_out: dict[str, HeldOut],
) -> None:
    """The step ``card``: the card's figures and ``MODEL_CARD.md`` for ``model`` in ``models_dir``, with the
    latency of the runtime a caller's detector runs."""
    test = f"{json.loads((run_dir / 'results.json').read_text())['dataset'].get('name')} test"
    figures = write_figures(run_dir, models_dir, held_out, frame_from=test if test in held_out else None)
    load = os.getloadavg()[0]
    frames, latency_source = latency_frames()
    fast = Detector.load(model)  # what a caller's detector runs: the default runtime
    write_model_card(
        run_dir,
        models_dir / CARD_NAME,
        model=model,
        detector=detector,
        rows=rows,
        figures=figures,
        latency=detector_latency(fast, frames, repeats=64),
        latency_source=latency_source,
        latency_runtime=runtime_description(fast.backend),
        load_average=load,
    )


def _gate_rows(
    detector: Detector, model: Path, models_dir: Path, held_out: dict[str, HeldOut]
) -> dict[str, dict]:
    """The step ``gate``: the regression gate's reference for ``model`` (``gate.json``) written, its card rows
    returned; the gate set's detections per mode go into ``held_out`` for its PR figure."""
    from rebar_data.perception.evaluation import gate
    from rebar_data.perception.training.gate_reference import write_reference

    with tempfile.TemporaryDirectory(prefix="rebar-gate-") as tmp:
        root = gate.build_gate_set(tmp)
        rows = gate.card_rows(write_reference(model, out=models_dir / gate.GATE_NAME, data_root=tmp))
        samples, _ = gate.load_gate_set(root)
        modes = {gate.MODE_NAMES[m]: p for m, p in gate.gate_predictions(detector, samples).items()}
        held_out[next(iter(rows)).rsplit(", ", 1)[0]] = HeldOut(samples, data.stated_oks_sigma(root), modes)
    return rows
