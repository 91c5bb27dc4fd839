"""The model card's rows: a model scored on its run's own splits (from the run's records), where the test
split's errors lie, the training dataset as a random frame split would test it, and every split of each
held-out dataset, each dataset's scoring a step kept in the run folder. The card itself is written by
:mod:`rebar_data.perception.training.card`."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from rebar_data.digest import sha256_file
from rebar_data.perception.evaluation import data, evaluate
from rebar_data.perception.evaluation.false_detections import false_detection_census
from rebar_data.perception.inference.detector import Detector
from rebar_data.resume import Steps, key_of

FLATTENED = "what lies behind flattened (`--flatten-behind`)"  # the rows read so


@dataclass
class HeldOut:
    """One held-out set's samples, its OKS sigma and, per input mode, the detections on each sample."""

    samples: list
    sigma: float
    modes: dict[str, list] = field(default_factory=dict)


def rgb_path(detector: Detector) -> str:
    """What scores a frame read without depth, in words."""
    return "the RGB stages and the line check" if detector.line_check else "the RGB stages alone"


def _flattened(detector: Detector, samples: Sequence, *, progress: bool) -> list | None:
    """The detections with depth and what lies behind the front bars flattened; None where it cannot be."""
    if detector.depth_check is None or not samples or any(s.depth_path is None for s in samples):
        return None
    before, detector.flatten_behind = detector.flatten_behind, True
    try:
        return evaluate.predict(detector, samples, progress=progress)
    finally:
        detector.flatten_behind = before


def _plain_preds(modes: dict[str, list]) -> dict[str, list]:
    return {m: [np.asarray(p, float).reshape(-1, 3).tolist() for p in preds] for m, preds in modes.items()}


def _arrays(modes: dict[str, list]) -> dict[str, list]:
    return {m: [np.asarray(p, float).reshape(-1, 3) for p in preds] for m, preds in modes.items()}


def _own_test_rows(
    detector: Detector, root: Path, test: list, name: str, sigma: float, progress: bool
) -> dict:
    """The training dataset's test split: where its errors lie, from RGB alone too, flattened."""
    predict, score = evaluate.predict, evaluate.score
    rows: dict[str, dict] = {}
    modes: dict[str, list] = {}
    preds = predict(detector, test, progress=progress)
    with_depth = detector.depth_check is not None and any(s.depth_path is not None for s in test)
    modes["with depth" if with_depth else "RGB"] = preds
    rows |= {
        f"{name} test, {part}": m for part, m in evaluate.breakdown(root, test, preds, sigma=sigma).items()
    }
    if with_depth:  # from RGB alone as well, split by scene: where the RGB path's errors lie
        modes["RGB only"] = rgb = predict(detector, test, depth=False, progress=progress)
        parts = evaluate.breakdown(root, test, rgb, sigma=sigma).items()
        rows |= {f"{name} test, without depth, {p}": m for p, m in parts if p.startswith("scenes")}
    if (flat := _flattened(detector, test, progress=progress)) is not None:
        rows[f"{name} test, {FLATTENED}"] = score(test, flat, sigma=sigma)
    return {"rows": rows, "modes": _plain_preds(modes)}


def _held_out_rows(
    detector: Detector, path: Path, label: str, engine: str, samples: list, sigma: float, progress: bool
) -> dict:
    """Every split of a dataset built from another config (``label``): an Open3D one as the training data is
    read, another renderer's from RGB alone, with depth, flattened and against the 3D crossing points."""
    predict, score = evaluate.predict, evaluate.score
    rows: dict[str, dict] = {}
    if engine == "open3d":
        preds = predict(detector, samples, progress=progress)
        rows[f"{label} (all splits)"] = score(samples, preds, sigma=sigma)
        with_depth = detector.depth_check is not None and any(s.depth_path is not None for s in samples)
        return {"rows": rows, "modes": _plain_preds({"with depth" if with_depth else "RGB": preds})}
    modes: dict[str, list] = {}
    modes["RGB only"] = preds = predict(detector, samples, depth=False, progress=progress)
    census = false_detection_census(path, samples, preds)
    rows[f"{label}, RGB only"] = {**score(samples, preds, sigma=sigma), "false_detections": census}
    parts = evaluate.breakdown(path, samples, preds, sigma=sigma).items()  # where its errors lie
    rows |= {f"{label}, RGB only, {p}": m for p, m in parts if p.startswith("scenes")}
    if (flat := _flattened(detector, samples, progress=progress)) is not None:
        modes["with depth"] = predict(detector, samples, progress=progress)  # as an RGB-D camera
        rows[f"{label}, with depth"] = score(samples, modes["with depth"], sigma=sigma)
        rows[f"{label}, with depth, {FLATTENED}"] = score(samples, flat, sigma=sigma)
    crossing = evaluate.load_splits(path, truth="crossing")
    rows[f"{label}, RGB only, vs 3D crossing points"] = score(crossing, preds, sigma=sigma)
    if detector.crossing_point is not None:  # the same, with the crossing-point stage's output
        found = evaluate.at_crossing_points(detector, samples, preds)
        rows[f"{label}, RGB only, crossing points vs 3D crossing points"] = score(
            crossing, found, sigma=sigma
        )
    return {"rows": rows, "modes": _plain_preds(modes)}


def _dataset_key(root: Path) -> str:
    """What a scoring step reads of a dataset: its path and its manifest (every file's SHA-256)."""
    manifest = root / "meta/manifest.parquet"
    return key_of(str(root.resolve()), sha256_file(manifest) if manifest.exists() else None)


def evaluation_rows(
    detector: Detector,
    run_dir: Path,
    *,
    evaluate_on: Sequence[str | Path] = (),
    random_split: bool = True,
    progress: bool = False,
    held_out: dict[str, HeldOut] | None = None,
    steps: Steps | None = None,
    model_key: str = "",
) -> dict[str, dict]:
    """The card's rows, row name -> :func:`~.metrics.summary`: the run's own splits (from its records), where
    the test split's errors lie (:func:`~.evaluate.breakdown`), the training dataset scored as a random frame
    split would test it, and every split of each dataset in ``evaluate_on`` (built with other configs; one
    rendered by another engine stands for a user's camera: scored from RGB alone, against the labels and the
    projected 3D crossing points). ``held_out`` receives each held-out set's detections per input mode. Each
    dataset's scoring is a step of ``steps`` (reused while ``model_key``, the model's files, and the dataset
    are the same)."""
    steps = steps if steps is not None else Steps(None)
    res = json.loads((run_dir / "results.json").read_text())
    held_out = {} if held_out is None else held_out
    sigma, name = res["oks_sigma"], res["dataset"].get("name")
    rows = {f"{name} {split}": m for split, m in sorted(res["results"].items(), reverse=True)}
    for split, m in sorted(res.get("results_without_depth", {}).items()):
        rows[f"{name} {split}, without depth ({rgb_path(detector)})"] = m
    for split, m in sorted(res.get("results_first_stage", {}).items()):
        rows[f"{name} {split}, first stage alone"] = m
    root = Path(res["dataset"].get("path") or "")
    built = (root / "tables/samples.parquet").exists()
    test = data.load_split(root, "test") if built else []
    if test:
        key = key_of(model_key, _dataset_key(root), sigma)
        done = steps.run(
            f"card: {name} test", key, lambda: _own_test_rows(detector, root, test, name, sigma, progress)
        )
        rows |= done["rows"]
        held_out.setdefault(f"{name} test", HeldOut(test, sigma)).modes.update(_arrays(done["modes"]))
    if random_split and built:

        def random_rows() -> dict:
            samples, trained = evaluate.random_frames(root)
            share = evaluate.RANDOM_SPLIT_FRACTION
            label = f"{name} random {share:.0%} of frames ({trained} of {len(samples)} trained on)"
            preds = evaluate.predict(detector, samples, progress=progress)
            return {label: evaluate.score(samples, preds, sigma=sigma)}

        rows |= steps.run(
            f"card: {name} random frames", key_of(model_key, _dataset_key(root), sigma), random_rows
        )
    for path in evaluate_on:
        path = data.check_dataset(path)
        info = data.read_info(path)
        label = f"{info.get('name') or path.parent.name} v{info.get('version', '?')}"
        engine, set_sigma = data.renderer_engine(info), data.stated_oks_sigma(path)
        samples = evaluate.load_splits(path)
        if engine != "open3d":
            label = f"{label}, {engine} renderer"
        key = key_of(model_key, _dataset_key(path), set_sigma)
        done = steps.run(
            f"card: {label}",
            key,
            partial(_held_out_rows, detector, path, label, engine, samples, set_sigma, progress),
        )
        rows |= done["rows"]
        seen = held_out.setdefault(
            label if engine != "open3d" else f"{label} (all splits)", HeldOut(samples, set_sigma)
        )
        seen.modes.update(_arrays(done["modes"]))
    return rows
