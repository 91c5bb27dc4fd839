"""The model card in the Hugging Face Hub's form (``card.md.j2``), written from a run's records and the rows
its scoring gives (:mod:`~rebar_data.perception.evaluation.card_rows`), its figures as small PNGs in
``models/card/``: training curves, a precision-recall figure per held-out set and one frame with its
detections drawn."""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path

import jinja2
import numpy as np
import yaml

from rebar_data.outputs import replace_file
from rebar_data.perception.evaluation import data, evaluate
from rebar_data.perception.evaluation.bench import DetectorLatency
from rebar_data.perception.evaluation.card_rows import FLATTENED, HeldOut, rgb_path
from rebar_data.perception.evaluation.false_detections import format_census
from rebar_data.perception.evaluation.metrics import keypoint_ap, oks_radius_px, pixel_metrics
from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.detector import OPERATING_THRESHOLD, Detector
from rebar_data.perception.inference.image import GAP_M, TOLERANCE
from rebar_data.timing import machine_description

CARD_NAME = "MODEL_CARD.md"
FIGURES_DIR = "card"  # the card's PNGs, beside it
RENDERER_NAMES = {"cycles": "Blender Cycles", "open3d": "Open3D"}
MODEL_INDEX_METRICS = {  # summary key -> the model index's metric name
    "oks_ap50": "OKS AP@0.5",
    "oks_ap": "OKS AP@0.5:0.95",
    "pck2": "PCK@2px",
    "median_px": "median error (px)",
    "recall_at_p99": "recall at precision 0.99",
}


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


def write_model_card(
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
    (:func:`~rebar_data.perception.evaluation.card_rows.evaluation_rows`) and ``figures``
    (:func:`write_figures`). ``detector`` is ``model`` loaded, as scored: its stages, score biases and weights
    are what the card states."""
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
        rgb_path=rgb_path(detector),
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
