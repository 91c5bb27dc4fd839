"""The detector's regression gate: the shipped model scored on a fixed held-out set
(``pipelines/detector-gate.yaml``) against its own reference (``gate.json``: :func:`reference`, which
shipping a model writes, :mod:`rebar_data.perception.training.gate_reference`).

AP@0.5, PCK@2px and recall@P0.99, with RGB alone and with the set's sensor depth, pass when at least the reference minus
``K_SE`` bootstrap standard errors over the set's scenes (why: ``docs/detector/design.md``, "The regression
gate")."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from rebar_data.config import PAPER_PIPELINE
from rebar_data.perception.evaluation.data import Sample, load_split, read_info, stated_oks_sigma
from rebar_data.perception.evaluation.evaluate import predict, truth_of
from rebar_data.perception.evaluation.metrics import keypoint_ap, pixel_metrics, summary
from rebar_data.perception.inference.detector import MODELS_DIR, Detector

GATE_PIPELINE = PAPER_PIPELINE.with_name("detector-gate.yaml")
GATE_NAME = "gate.json"
GATE_FILE = MODELS_DIR / GATE_NAME
FIGURES = ("oks_ap50", "pck2", "recall_at_p99")
MODES = {"rgb": False, "rgbd": True}  # mode -> whether the detector reads the depth image
MODE_NAMES = {"rgb": "RGB only", "rgbd": "with depth"}  # depth: the set's sensor depth
RUNTIME = "onnxruntime"  # the gate scores `Detector.load(runtime=RUNTIME)`
K_SE = 3.0
BOOTSTRAP_REPLICATES = 1000
BOOTSTRAP_SEED = 0
# the files whose hashes make the set's digest
SET_FOLDERS = ("images/", "depth/", "sensor_depth/", "labels/")


def build_gate_set(out_root: str | Path, *, workers: int = 1) -> Path:
    """Build ``pipelines/detector-gate.yaml`` under ``out_root`` (or find it built) and return its folder."""
    from rebar_data.dataset.build import build_dataset
    from rebar_data.dataset.layout import dataset_dir
    from rebar_data.pipeline import load_pipeline

    cfg = load_pipeline(GATE_PIPELINE)
    final = dataset_dir(Path(out_root), cfg.name, cfg.version)
    if (final / "meta/manifest.parquet").exists():
        return final
    return build_dataset(GATE_PIPELINE, out_root, workers=workers)


def load_gate_set(root: str | Path) -> tuple[list[Sample], list[str]]:
    """The set's images (its test split) and each one's scene id, in the samples table's order."""
    samples = load_split(root, "test")
    table = pq.read_table(Path(root) / "tables/samples.parquet", columns=["image_id", "scene_id"])
    scene_of = dict(zip(table["image_id"].to_pylist(), table["scene_id"].to_pylist(), strict=True))
    return samples, [scene_of[s.image_id] for s in samples]


def set_digest(root: str | Path) -> str:
    """SHA-256 over the manifest's hashes of the set's images, depth and labels (:data:`SET_FOLDERS`)."""
    table = pq.read_table(Path(root) / "meta/manifest.parquet", columns=["path", "sha256"])
    rows = sorted(
        f"{p} {h}\n"
        for p, h in zip(table["path"].to_pylist(), table["sha256"].to_pylist(), strict=True)
        if p.startswith(SET_FOLDERS)
    )
    return hashlib.sha256("".join(rows).encode()).hexdigest()


def gate_predictions(detector: Detector, samples: Sequence[Sample]) -> dict[str, list[np.ndarray]]:
    """Mode -> the detector's detections on every sample, as the metrics read them."""
    return {mode: predict(detector, samples, depth=depth) for mode, depth in MODES.items()}


def measure(detector: Detector, root: str | Path) -> dict[str, dict[str, float]]:
    """Mode -> the gate's figures (``FIGURES``) of ``detector`` on the built set at ``root``."""
    samples, _ = load_gate_set(root)
    truths, sigma = [truth_of(s) for s in samples], stated_oks_sigma(root)
    found = {mode: summary(truths, p, sigma=sigma) for mode, p in gate_predictions(detector, samples).items()}
    return {mode: {f: m[f] for f in FIGURES} for mode, m in found.items()}


def bootstrap_se(
    samples: Sequence[Sample],
    predictions: Sequence[np.ndarray],
    groups: Sequence[str],
    *,
    sigma: float,
    replicates: int = BOOTSTRAP_REPLICATES,
    seed: int = BOOTSTRAP_SEED,
) -> dict[str, float]:
    """Standard error of each of ``FIGURES``: the standard deviation of the figure over ``replicates`` sets
    drawn from ``groups`` (one label per sample, e.g. its scene) with replacement, whole groups at a time."""
    truths = [truth_of(s) for s in samples]
    names = sorted(set(groups))
    members = [np.flatnonzero(np.asarray(groups) == g) for g in names]
    rng = np.random.default_rng(seed)
    drawn = {f: np.empty(replicates) for f in FIGURES}
    for r in range(replicates):
        pick = np.concatenate([members[i] for i in rng.integers(0, len(names), len(names))])
        t = [truths[i] for i in pick]
        p = [predictions[i] for i in pick]
        px = pixel_metrics(t, p)  # and AP@0.5 from OKS 0.5 alone: the same as from all ten thresholds
        drawn["oks_ap50"][r] = keypoint_ap(t, p, sigma=sigma, thresholds=np.array([0.5])).ap50
        drawn["pck2"][r] = px.pck[2.0]
        drawn["recall_at_p99"][r] = px.recall_at_p99
    return {f: float(np.std(v, ddof=1)) for f, v in drawn.items()}


def reference(
    detector: Detector,
    root: str | Path,
    *,
    replicates: int = BOOTSTRAP_REPLICATES,
    seed: int = BOOTSTRAP_SEED,
) -> dict:
    """What ``gate.json`` holds for ``detector`` on the built set at ``root``: per mode the figures, their
    bootstrap SEs, margins (``K_SE`` SEs), floors (figure - margin), every headline figure, their source."""
    from rebar_data.digest import sha256_file

    samples, scenes = load_gate_set(root)
    sigma = stated_oks_sigma(root)
    info = read_info(root)
    modes = {}
    for mode, preds in gate_predictions(detector, samples).items():
        m = summary([truth_of(s) for s in samples], preds, sigma=sigma)
        fig = {f: m[f] for f in FIGURES}
        se = bootstrap_se(samples, preds, scenes, sigma=sigma, replicates=replicates, seed=seed)
        margin = {f: K_SE * se[f] for f in FIGURES}
        floor = {f: fig[f] - margin[f] for f in FIGURES}
        modes[mode] = dict(depth=MODES[mode], figures=fig, se=se, margin=margin, floor=floor, summary=m)
    path = detector.path
    return {
        "model": {"file": path.name if path else None, "sha256": sha256_file(path) if path else None},
        "runtime": detector.backend,
        "reading": detector.reading,
        "set": {
            "pipeline": f"pipelines/{GATE_PIPELINE.name}",
            "name": info.get("name"),
            "version": info.get("version"),
            "seed": info.get("seed"),
            "images": len(samples),
            "scenes": len(set(scenes)),
            "visible_crossings": int(sum(len(s.visible) for s in samples)),
            "oks_sigma": sigma,
            "digest": set_digest(root),
        },
        "margin_rule": {
            "k_se": K_SE,
            "se": "bootstrap over the set's scenes (whole scenes drawn with replacement)",
            "replicates": replicates,
            "seed": seed,
        },
        "modes": modes,
    }


def read_reference(path: str | Path = GATE_FILE) -> dict:
    return json.loads(Path(path).read_text())


def card_rows(path: str | Path = GATE_FILE) -> dict[str, dict]:
    """The model card's rows for the gate set, one per mode: row name -> every headline figure."""
    ref = read_reference(path)
    label = f"{ref['set']['name']} v{ref['set']['version']} (the regression gate's set)"
    return {f"{label}, {MODE_NAMES[mode]}": entry["summary"] for mode, entry in ref["modes"].items()}


def failures(measured: dict[str, dict[str, float]], ref: dict) -> list[str]:
    """One line for each figure of each of the reference's modes under its floor (none: the gate passes)."""
    out = []
    for mode, entry in ref["modes"].items():
        for f in FIGURES:
            got, floor = measured[mode][f], entry["floor"][f]
            if not got >= floor:
                out.append(
                    f"{mode} {f} {got:.4f} < {floor:.4f} (reference {entry['figures'][f]:.4f} - margin "
                    f"{entry['margin'][f]:.4f}, {ref['margin_rule']['k_se']:g} bootstrap SEs)"
                )
    return out
