"""Shipping a trained model with the package: its files copied into the models folder, its card's rows
scored, the regression gate's reference written beside it, its card and figures written."""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from rebar_data.config import ConfigError
from rebar_data.outputs import replace_file
from rebar_data.perception.evaluation import data
from rebar_data.perception.evaluation.bench import detector_latency, latency_frames, runtime_description
from rebar_data.perception.evaluation.card_rows import HeldOut, evaluation_rows
from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.detector import MODELS_DIR, SHIPPED_MODEL, Detector
from rebar_data.perception.training.card import CARD_NAME, write_card, write_figures
from rebar_data.resume import STEPS_FILE, Steps, key_of

MAX_SHIPPED_BYTES = 5 * 1024 * 1024


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
    detector = Detector.load(dst, runtime="onnxruntime")  # the card's figures: float32, as trained
    held_out: dict[str, HeldOut] = {}
    # each dataset's scoring is a step kept in the run folder: a ship run again after a kill reuses it
    steps = Steps(run_dir / STEPS_FILE, log=(lambda m: print(m, file=sys.stderr)) if progress else None)
    model_key = key_of([model_file.sha256_file(f) for f in (dst, *model_file.stage_files(dst)) if f.exists()])
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
    test = f"{json.loads((run_dir / 'results.json').read_text())['dataset'].get('name')} test"
    figures = write_figures(run_dir, models_dir, held_out, frame_from=test if test in held_out else None)
    load = os.getloadavg()[0]
    frames, latency_source = latency_frames()
    fast = Detector.load(dst)  # what a caller's detector runs: the default runtime
    write_card(
        run_dir,
        models_dir / CARD_NAME,
        model=dst,
        detector=detector,
        rows=rows,
        figures=figures,
        latency=detector_latency(fast, frames, repeats=64),
        latency_source=latency_source,
        latency_runtime=runtime_description(fast.backend),
        load_average=load,
    )
    return dst


def _gate_rows(
    detector: Detector, model: Path, models_dir: Path, held_out: dict[str, HeldOut]
) -> dict[str, dict]:
    """Write the regression gate's reference for ``model`` (``gate.json``) and return its card rows; the gate
    set's detections per mode go into ``held_out`` for its PR figure."""
    from rebar_data.perception.evaluation import gate
    from rebar_data.perception.training.gate_reference import write_reference

    with tempfile.TemporaryDirectory(prefix="rebar-gate-") as tmp:
        root = gate.build_gate_set(tmp)
        rows = gate.card_rows(write_reference(model, out=models_dir / gate.GATE_NAME, data_root=tmp))
        samples, _ = gate.load_gate_set(root)
        modes = {gate.MODE_NAMES[m]: p for m, p in gate.gate_predictions(detector, samples).items()}
        held_out[next(iter(rows)).rsplit(", ", 1)[0]] = HeldOut(samples, data.stated_oks_sigma(root), modes)
    return rows
