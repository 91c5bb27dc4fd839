"""Ship a trained model with the package: its ONNX files and a model card in the Hugging Face Hub's form
(``card.md.j2``) written from the run's records, its figures as small PNGs in ``models/card/``: training
curves, a precision-recall figure per held-out set and one frame with its detections drawn."""

from __future__ import annotations

import json
import os
import re
import shutil
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import jinja2
import numpy as np
import yaml

from rebar_data.config import ConfigError
from rebar_data.outputs import replace_file
from rebar_data.perception.evaluation import data, evaluate
from rebar_data.perception.evaluation.bench import (
    DetectorLatency,
    detector_latency,
    latency_frames,
    runtime_description,
)
from rebar_data.perception.evaluation.false_detections import false_detection_census, format_census
from rebar_data.perception.evaluation.metrics import keypoint_ap, oks_radius_px, pixel_metrics
from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.detector import MODELS_DIR, OPERATING_THRESHOLD, SHIPPED_MODEL, Detector
from rebar_data.perception.inference.image import GAP_M, TOLERANCE
from rebar_data.resume import STEPS_FILE, Steps, key_of
from rebar_data.timing import machine_description

MAX_SHIPPED_BYTES = 5 * 1024 * 1024
CARD_NAME = "MODEL_CARD.md"
FIGURES_DIR = "card"  # the card's PNGs, beside it
FLATTENED = "what lies behind flattened (`--flatten-behind`)"  # the rows read so
RENDERER_NAMES = {"cycles": "Blender Cycles", "open3d": "Open3D"}
MODEL_INDEX_METRICS = {  # summary key -> the model index's metric name
    "oks_ap50": "OKS AP@0.5",
    "oks_ap": "OKS AP@0.5:0.95",
    "pck2": "PCK@2px",
    "median_px": "median error (px)",
    "recall_at_p99": "recall at precision 0.99",
}


@dataclass
class HeldOut:
    """One held-out set's samples, its OKS sigma and, per input mode, the detections on each sample."""

    samples: list
    sigma: float
    modes: dict[str, list] = field(default_factory=dict)


def pr_figure_name(set_name: str) -> str:
    """The file name of a held-out set's PR figure: its name before any parenthesis, as a slug."""
    return "pr-" + re.sub(r"[^a-z0-9]+", "-", set_name.split(" (")[0].lower()).strip("-") + ".png"


def write_figures(
    run_dir: Path, card_dir: Path, held_out: dict[str, HeldOut], *, frame_from: str | None
) -> dict:
    """Write the card's PNGs to ``card_dir / FIGURES_DIR`` (what was there before removed first) and return
    their links, relative to the card: ``training``, the run's curves; ``pr``, held-out set -> a PR figure, a
    curve per input mode; ``frame``, the frame of ``frame_from`` with the most visible crossings, with its
    detections in its first mode (and what the caption says of it)."""
    from rebar_data.perception.evaluation.plots import plot_history, plot_pr_modes, read_history, write_frame

    folder = card_dir / FIGURES_DIR
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.png"):
        old.unlink()
    out: dict = {"training": None, "pr": {}, "frame": None}
    if (run_dir / "metrics.csv").exists():
        res = json.loads((run_dir / "results.json").read_text())
        stages = {"second stage": "refine", "depth check": "depth_check", "crossing point": "crossing_point"}
        path = plot_history(
            read_history(run_dir / "metrics.csv"),
            folder / "training.png",
            stages={name: res.get(f"{key}_history") or [] for name, key in stages.items()},
            adapt=res.get("adapt_history") or [],
            best_epoch=res.get("best_epoch"),
        )
        out["training"] = f"{FIGURES_DIR}/{path.name}"
    for name, h in held_out.items():
        if h.samples and h.modes:
            truths = [evaluate.truth_of(s) for s in h.samples]
            curves = {
                m: (keypoint_ap(truths, p, sigma=h.sigma), pixel_metrics(truths, p))
                for m, p in h.modes.items()
            }
            subtitle = f"{len(h.samples)} images, {sum(len(t.uv) for t in truths)} visible crossings, OKS 0.5"
            path = plot_pr_modes(curves, folder / pr_figure_name(name), title=name, subtitle=subtitle)
            out["pr"][name] = f"{FIGURES_DIR}/{path.name}"
    if frame_from in held_out and held_out[frame_from].samples:
        h = held_out[frame_from]
        mode, preds = next(iter(h.modes.items()))
        k = max(range(len(h.samples)), key=lambda i: len(h.samples[i].visible))
        s, p = h.samples[k], np.asarray(preds[k]).reshape(-1, 3)
        rgb = data.read_image(s.path)
        path, scale = write_frame(rgb, p, folder / "frame.png", truth=s.visible, occluded=s.occluded)
        found = int((p[:, 2] >= OPERATING_THRESHOLD).sum())
        out["frame"] = dict(
            link=f"{FIGURES_DIR}/{path.name}", set=frame_from, sample=s, mode=mode, found=found, scale=scale
        )
    return out


def renderers(ds: dict) -> tuple[str, str, int]:
    """The renderer of a run's dataset, and the other renderers of its supplements with their frames
    (a dataset record that names no renderer was Open3D's)."""

    def name(d: dict) -> str:
        engine = d.get("renderer") or "open3d"
        return RENDERER_NAMES.get(engine, engine)

    supplements = (ds.get("supplements") or []) + (ds.get("refine_supplements") or [])
    other = [d for d in supplements if name(d) != name(ds)]
    others = " and ".join(sorted({name(d) for d in other}))
    return name(ds), others, sum(int(d.get("images") or 0) for d in other)


def stage_rows(model: Path, detector: Detector, res: dict) -> list[tuple[str, ...]]:
    """The card's table of the model's files: stage, file, size, parameters, what the settings do not say."""
    rows = [("first stage", model, res.get("parameters"), "the heatmap network (`model` below)")]
    if detector.refiner is not None:
        second = "the patch network (`refine` below)"
        rows.append(("second stage", model_file.refiner_path(model), res.get("refiner_parameters"), second))
        if detector.refiner.int8_run is not None:
            cal = detector.meta["refiner"].get("int8_calibrated_on", {})
            sets = ", ".join(f"`{d}`" for d in cal.get("data", [])) or "the training images"
            int8 = f"read by the later passes; calibrated on {cal.get('patches', '?')} patches of {sets}"
            rows.append(("second stage, int8 copy", model_file.int8_passes_path(model), "(the same)", int8))
    if detector.depth_check is not None:
        depth, path = "read with a depth image (`depth_check` below)", model_file.depth_check_path(model)
        rows.append(("depth check", path, res.get("depth_check_parameters"), depth))
    if detector.crossing_point is not None:
        point = 'only with `point="crossing"` (`crossing_point` below)'
        path = model_file.crossing_point_path(model)
        rows.append(("crossing point", path, res.get("crossing_point_parameters"), point))
    if detector.line_check is not None:
        e = detector.meta.get("line_check", {})
        fitted = ", ".join(f"`{d}`" for d in e.get("fitted_on", [])) or "its fitting images"
        line = f"a logistic regression fitted on {e.get('candidates', '?')} candidates of {fitted}"
        rows.append(("line check", None, str(len(detector.line_check.weights) + 1), line))
    return [
        (
            stage,
            f"`{path.name}`" if path else "(in the model's metadata)",
            f"{path.stat().st_size / 1024:.0f} KiB" if path else "-",
            n if isinstance(n, str) else f"{n / 1e3:.0f} k" if n else "-",
            notes,
        )
        for stage, path, n, notes in rows
    ]


def _lone_crossing_scores(detector: Detector, own: Sequence[float] = (0.9, 0.6, 0.5)) -> list[tuple]:
    """What the line check makes of a crossing with no other candidate along its bars: (score in, out)."""
    from rebar_data.perception.inference.checks import features

    check = detector.line_check
    x = features(np.asarray(own, float), np.full((len(own), 2, 1), -1))
    return list(zip(own, (1.0 / (1.0 + np.exp(-(x @ check.weights + check.bias)))).tolist(), strict=True))


def table_rows(rows: dict[str, dict], default_input: str) -> list[tuple[str, str, dict]]:
    """(set, input, metrics) of each row, each set's rows together in the order the sets first appear. The
    input is the part of a row's name after the set's (``"crossval-planar v1.1.0, cycles renderer, RGB
    only"``: ``"cycles renderer, RGB only"``), led by ``default_input`` where it names no mode."""
    groups: dict[str, list[tuple[str, str, dict]]] = {}
    for name, m in rows.items():
        head, _, rest = name.partition(", ")
        if not any(w in rest for w in ("depth", "RGB", "first stage alone")):
            rest = f"{default_input}; {rest}" if rest else default_input
        groups.setdefault(head, []).append((head, rest, m))
    return [r for g in groups.values() for r in g]


def model_index(rows: list[tuple[str, str, dict]], ds: dict, *, default_input: str) -> dict:
    """The card's YAML metadata beyond the template's: the training datasets and the model index, each
    held-out set in each input mode with its headline figures (not the val split, trained frames or parts)."""
    results = []
    for head, rest, m in rows:
        whole = (
            rest in (default_input, "RGB only", "with depth")
            or rest.startswith("without depth (")
            or rest.endswith(("renderer, RGB only", "renderer, with depth"))
        )
        if not whole or head.endswith(" val") or " random " in head:
            continue
        name = head.split(" (")[0]
        split = name.rsplit(" ", 1)[1] if name.endswith((" test", " val")) else "all"
        results.append(
            {
                "task": {"type": "keypoint-detection", "name": "Rebar crossing detection"},
                "dataset": {"name": f"{head}, {rest}", "type": name.split(" ")[0], "split": split},
                "metrics": [  # a median error with no match is NaN: the table shows it, the index not
                    {"type": k, "name": n, "value": round(float(m[k]), 4)}
                    for k, n in MODEL_INDEX_METRICS.items()
                    if np.isfinite(m[k])
                ],
            }
        )
    supplements = (ds.get("supplements") or []) + (ds.get("refine_supplements") or [])
    datasets = list(dict.fromkeys(n for n in [ds.get("name")] + [d.get("name") for d in supplements] if n))
    return {"datasets": datasets, "model-index": [{"name": "rebar-keypoint", "results": results}]}


def _template() -> jinja2.Template:
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(Path(__file__).parent),
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
        undefined=jinja2.StrictUndefined,
    )
    env.filters.update(f=format, census=format_census, json=lambda v: json.dumps(v, sort_keys=True))
    env.filters["named"] = lambda sets: ", ".join(
        f"`{d['name']}` v{d['version']} ({d['images']} images)" for d in sets
    )
    env.globals.update(
        docs="../../../docs/detector",  # relative to rebar_data/perception/models/
        border_px=evaluate.BORDER_BAND_PX,
        lower_mat_column=evaluate.LOWER_MAT_COLUMN,
        flattened=FLATTENED,
        gap_m=GAP_M,
        tolerance=TOLERANCE,
    )
    return env.get_template("card.md.j2")


def write_card(
    run_dir: Path,
    path: Path,
    *,
    model: Path,
    detector: Detector,
    rows: dict[str, dict],
    figures: dict,
    latency: DetectorLatency,
    latency_source: str,
    latency_runtime: str,
    load_average: float | None = None,
) -> Path:
    """Render the model card (``card.md.j2``) to ``path`` from the run's records, ``rows``
    (:func:`evaluation_rows`) and ``figures`` (:func:`write_figures`). ``detector`` is ``model`` loaded, as
    scored: its stages, score biases and weights are what the card states."""
    res = json.loads((run_dir / "results.json").read_text())
    tc = json.loads((run_dir / "config.json").read_text())["train_config"]
    default_input = "with depth" if detector.depth_check is not None else "RGB"
    table = table_rows(rows, default_input)
    meta = model_index(table, res["dataset"], default_input=default_input)
    later = sum(res.get(f"{k}_seconds", 0.0) for k in ("adapt", "refine", "depth_check", "crossing_point"))
    text = _template().render(
        # the lists and maps of plain values on one line each
        model_index=yaml.safe_dump(meta, sort_keys=False, width=110, default_flow_style=None).rstrip(),
        detector=detector,
        depth=detector.depth_check is not None,
        verifies=bool(detector.refiner is not None and (tc.get("refine") or {}).get("verify")),
        rgb_path=_rgb_path(detector),
        stages=stage_rows(model, detector, res),
        lone=_lone_crossing_scores(detector) if detector.line_check is not None else [],
        ds=res["dataset"],
        res=res,
        tc=tc,
        first_minutes=(res["train_seconds_total"] - later) / 60,
        renderers=renderers(res["dataset"]),
        oks_radius=lambda box: oks_radius_px(res["oks_sigma"], box),
        rows=table,
        has=lambda marker: any(marker in name for name in rows),
        census={n: m["false_detections"] for n, m in rows.items() if m.get("false_detections")},
        figures=figures,
        latency=latency,
        latency_source=latency_source,
        latency_runtime=latency_runtime,
        load_average=load_average,
        machine=machine_description(),
    )
    return replace_file(path, lambda tmp: tmp.write_text(text))


def _rgb_path(detector: Detector) -> str:
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
    return key_of(str(root.resolve()), model_file.sha256_file(manifest) if manifest.exists() else None)


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
        rows[f"{name} {split}, without depth ({_rgb_path(detector)})"] = m
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

    with tempfile.TemporaryDirectory(prefix="rebar-gate-") as tmp:
        root = gate.build_gate_set(tmp)
        rows = gate.card_rows(gate.write_reference(model, out=models_dir / gate.GATE_NAME, data_root=tmp))
        samples, _ = gate.load_gate_set(root)
        modes = {gate.MODE_NAMES[m]: p for m, p in gate.gate_predictions(detector, samples).items()}
        held_out[next(iter(rows)).rsplit(", ", 1)[0]] = HeldOut(samples, data.stated_oks_sigma(root), modes)
    return rows
