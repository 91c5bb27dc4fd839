"""Ship a trained model with the package: its ONNX files and a model card in the Hugging Face Hub's form (YAML
header with the model index, then model details, intended use and limits, training data, one evaluation table,
how to use, latency), written from the run's own records, with its figures as small PNGs in ``models/card/``:
the training curves, a precision-recall figure per held-out set and one frame with its detections drawn."""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.bench import DetectorLatency, detector_latency, latency_frames
from rebar_data.perception.evaluation.data import (
    check_dataset,
    load_split,
    read_info,
    renderer_engine,
    stated_oks_sigma,
)
from rebar_data.perception.evaluation.evaluate import (
    BORDER_BAND_PX,
    LOWER_MAT_COLUMN,
    at_crossing_points,
    predict,
)
from rebar_data.perception.evaluation.metrics import oks_radius_px
from rebar_data.perception.inference.detector import (
    DUPLICATE_PX,
    MODELS_DIR,
    OPERATING_THRESHOLD,
    SHIPPED_MODEL,
    Detector,
)
from rebar_data.perception.inference.image import GAP_M, TOLERANCE
from rebar_data.perception.inference.model_file import (
    crossing_point_path,
    depth_check_path,
    int8_passes_path,
    refiner_path,
    runtime_description,
    stage_files,
)
from rebar_data.timing import machine_description

MAX_SHIPPED_BYTES = 5 * 1024 * 1024
CARD_NAME = "MODEL_CARD.md"
FIGURES_DIR = "card"  # the card's PNGs, beside it
MODEL_NAME = "rebar-keypoint"
LICENSE = "other"  # the Hub's id when a card names no standard license
LICENSE_NAME = "none-declared"
DESIGN_DOC = "docs/detector/design.md"
EXPERIMENTS_DOC = "docs/detector/experiments.md"
DOCS_FROM_CARD = "../../../docs/detector"  # the docs folder, relative to rebar_data/perception/models/
FLATTENED = "what lies behind flattened (`--flatten-behind`)"  # the rows read so
RENDERER_NAMES = {"cycles": "Blender Cycles", "open3d": "Open3D"}


def _step(refine: dict) -> str:
    step = float(refine.get("step", 1.0))
    return "all the way" if step == 1.0 else f"{step:g} of the way"


def _named(supplements: list[dict]) -> str:
    """Supplement datasets as the card names them: name, version and images of each."""
    return ", ".join(f"`{d.get('name')}` v{d.get('version')} ({d.get('images')} images)" for d in supplements)


def _supplement_lines(supplements: list[dict]) -> list[str]:
    """The card's words on the further datasets a run trained on, if any."""
    if not supplements:
        return []
    return [
        f"- Also trained on every image of {_named(supplements)} (`pipelines/<name>.yaml`): scenes of their own,",
        "  none of them in the val or test split above.",
    ]


def _refine_supplement_lines(
    supplements: list[dict], refine: dict, adapted: bool, first_epochs_repeats: int = 0
) -> list[str]:
    """The card's words on the datasets the second stage (and the first stage's adapt epochs, and with
    ``TrainConfig.other_renderer_repeats`` its first epochs) trained on, if any."""
    if not supplements:
        return []
    if first_epochs_repeats:
        seen = f" saw them listed {first_epochs_repeats} times in its first epochs" + (
            ", and in its adapt epochs." if adapted else "."
        )
    else:
        seen = " saw them only in its adapt epochs." if adapted else " never saw them."
    return [
        f"  It also trained on every image of {_named(supplements)}, each listed "
        f"{refine.get('supplement_repeats', 1)} times",
        "  (`pipelines/<name>.yaml`; scenes of their own, rendered as the pipeline file says); the first stage"
        + seen,
    ]


def _renderer(d: dict) -> str:
    """The renderer a run's dataset record names; runs before records named it trained on Open3D's."""
    engine = d.get("renderer") or "open3d"
    return RENDERER_NAMES.get(engine, engine)


def _renderer_line(ds: dict) -> str:
    """The card's words on which renderers drew the training images."""
    main = _renderer(ds)
    other = [
        d
        for d in (ds.get("supplements") or []) + (ds.get("refine_supplements") or [])
        if _renderer(d) != main
    ]
    if not other:
        return f"- Trained on rendered images only, all from one renderer ({main}); no real photographs were seen."
    frames = sum(int(d.get("images") or 0) for d in other)
    return (
        f"- Trained on rendered images only: from {main}, and {frames} frames from "
        f"{' and '.join(sorted({_renderer(d) for d in other}))} (the datasets named above); no real photographs "
        "were seen."
    )


def _distractor_gain_lines(augment: dict) -> list[str]:
    """The distractor gain's line, when the run used it (``AugmentConfig.distractor_gain``)."""
    share = augment.get("distractor_gain_probability", 0.0)
    if not share:
        return []
    lo, hi = augment["distractor_gain"]
    return [
        f"- For {share:.0%} of the crops and second-stage patches, the pixels the instance map gives to the"
        f" distractors (the lower mat above all) scaled by one factor in [{lo:g}, {hi:g}]: the renderer lights"
        " the lower mat darker than Cycles does, and without it the detector took a brighter lower mat's"
        " crossings for the top mat's."
    ]


def _adapt_lines(res: dict, tc: dict, ds: dict) -> list[str]:
    """The card's words on the first stage's adapt epochs, if it had any."""
    if not res.get("adapt_epochs"):
        return []
    a = tc["adapt"]
    return [
        f"- Adapt epochs: {res['adapt_epochs']} more after the best epoch "
        f"({res.get('adapt_seconds', 0.0) / 60:.1f} minutes, in the total above), on the training images and",
        f"  every image of {_named(ds.get('refine_supplements') or [])}, each listed {a['supplement_repeats']} times;",
        f"  AdamW from lr {a['lr']:g} down a cosine, the batch norms' statistics frozen, no mosaic. The first stage",
        "  shipped is the adapted one.",
        *(
            [
                f"  The cells at the crossings a lower mat shows (its own, and top bars in front of its bars; placed "
                f"from the tables) weigh {a['lower_mat_weight']:g} in the heatmap loss."
            ]
            if a.get("lower_mat_weight", 1.0) != 1.0
            else []
        ),
    ]


@dataclass
class HeldOut:
    """One held-out set's detections as the card scored them: its samples, its OKS sigma and, per input mode,
    the detections on each sample."""

    samples: list
    sigma: float
    modes: dict[str, list] = field(default_factory=dict)


@dataclass
class CardFigures:
    """The card's PNGs as links relative to the card: one frame with its detections drawn, the training
    curves, and a precision-recall figure per held-out set (set -> link)."""

    frame: str | None = None
    frame_caption: str = ""
    training: str | None = None
    pr: dict[str, str] = field(default_factory=dict)


def pr_figure_name(set_name: str) -> str:
    """The file name of a held-out set's PR figure: its name before any parenthesis, as a slug."""
    return "pr-" + re.sub(r"[^a-z0-9]+", "-", set_name.split(" (")[0].lower()).strip("-") + ".png"


def frame_figure(
    held_out: HeldOut, set_name: str, folder: Path, *, name: str = "frame.png"
) -> tuple[Path, str]:
    """Draw the held-out set's frame with the most visible crossings and its detections in its first mode
    (:func:`~rebar_data.perception.evaluation.plots.write_frame`); returns the file and its caption."""
    from rebar_data.perception.evaluation.data import read_image
    from rebar_data.perception.evaluation.plots import write_frame

    mode, preds = next(iter(held_out.modes.items()))
    k = max(range(len(held_out.samples)), key=lambda i: len(held_out.samples[i].visible))
    s, p = held_out.samples[k], np.asarray(preds[k]).reshape(-1, 3)
    path, scale = write_frame(read_image(s.path), p, folder / name, truth=s.visible, occluded=s.occluded)
    found = int((p[:, 2] >= OPERATING_THRESHOLD).sum())
    caption = (
        f"{set_name}, image `{s.image_id}` ({mode}): {len(s.visible)} visible crossings (green circles; occluded "
        f"ones blue), {found} detections of score >= {OPERATING_THRESHOLD:g} (red crosses)"
        + (f"; drawn at {scale:.2f} of its size" if scale != 1.0 else "")
        + "."
    )
    return path, caption


def pr_figure(held_out: HeldOut, set_name: str, path: Path) -> Path:
    """The held-out set's precision-recall figure, a curve per input mode
    (:func:`~rebar_data.perception.evaluation.plots.plot_pr_modes`)."""
    from rebar_data.perception.evaluation.evaluate import truth_of
    from rebar_data.perception.evaluation.metrics import keypoint_ap, pixel_metrics
    from rebar_data.perception.evaluation.plots import plot_pr_modes

    truths = [truth_of(s) for s in held_out.samples]
    curves = {
        mode: (keypoint_ap(truths, preds, sigma=held_out.sigma), pixel_metrics(truths, preds))
        for mode, preds in held_out.modes.items()
    }
    n = sum(len(t.uv) for t in truths)
    return plot_pr_modes(
        curves,
        path,
        title=set_name,
        subtitle=f"{len(held_out.samples)} images, {n} visible crossings, OKS 0.5",
    )


def training_figure(run_dir: Path, path: Path) -> Path | None:
    """The run's training curves (``metrics.csv`` and the later stages' records in ``results.json``), or
    None when the run folder has no ``metrics.csv``."""
    from rebar_data.perception.evaluation.plots import plot_training, read_history

    if not (run_dir / "metrics.csv").exists():
        return None
    res = json.loads((run_dir / "results.json").read_text())
    stages = {
        "second stage": res.get("refine_history") or [],
        "depth check": res.get("depth_check_history") or [],
        "crossing point": res.get("crossing_point_history") or [],
    }
    return plot_training(
        read_history(run_dir / "metrics.csv"),
        path,
        stages=stages,
        adapt=res.get("adapt_history") or [],
        best_epoch=res.get("best_epoch"),
    )


def write_figures(
    run_dir: Path, card_dir: Path, held_out: dict[str, HeldOut], *, frame_from: str | None
) -> CardFigures:
    """Write the card's PNGs to ``card_dir / FIGURES_DIR`` (what was there before removed first): the training
    curves, a PR figure per held-out set in ``held_out`` and one frame of ``frame_from`` with its detections."""
    folder = card_dir / FIGURES_DIR
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.png"):
        old.unlink()
    out = CardFigures()
    training = training_figure(run_dir, folder / "training.png")
    if training is not None:
        out.training = f"{FIGURES_DIR}/{training.name}"
    for name, h in held_out.items():
        if h.samples and h.modes:
            path = pr_figure(h, name, folder / pr_figure_name(name))
            out.pr[name] = f"{FIGURES_DIR}/{path.name}"
    if frame_from in held_out and held_out[frame_from].samples:
        path, out.frame_caption = frame_figure(held_out[frame_from], frame_from, folder)
        out.frame = f"{FIGURES_DIR}/{path.name}"
    return out


def _kib(path: Path) -> str:
    return f"{path.stat().st_size / 1024:.0f} KiB"


def _params(n: float | None) -> str:
    return f"{n / 1e3:.0f} k" if n else "-"


def _second_stage_cell(refine: dict, detector: Detector, *, with_depth: str) -> str:
    """What the second stage does as shipped: one table cell of its settings and how scores combine."""
    parts = [
        f"moves each detection onto the crossing its {refine['patch_px']} px patch shows (offset from the patch centre)"
    ]
    if refine.get("verify"):
        parts.append(
            "and gives the logit p that the patch shows a crossing at all; score = sigmoid(first-stage logit + "
            f"{detector.verify_power:g} log p{with_depth}), so it only lowers scores"
        )
    if refine.get("border", "mirror") == "mask":
        parts.append(
            "beyond the image border its patch is blank, with a channel marking the image, so it places a crossing"
            " centred just outside the frame, and such a detection is dropped"
        )
    if refine.get("context_scale", 0):
        parts.append(
            f"also reads the {refine['context_scale']} times wider square, shrunk to {refine['patch_px']} px"
        )
    if refine.get("views", 1) > 1:
        first = refine.get("first_pass_views", refine["views"])
        parts.append(
            f"{refine['views']} views a patch (turned, flipped; offsets averaged)"
            + (f", {first} in its first pass" if first != refine["views"] else "")
        )
    if refine.get("iterations", 1) > 1:
        parts.append(
            f"{refine['iterations']} passes, each later one moving the point {_step(refine)}; a detection within "
            f"{DUPLICATE_PX:g} px of a better one dropped"
        )
        if refine.get("shrink_above_px"):
            lo, hi = refine["shrink_above_px"]
            parts.append(
                "its first pass also gives each crossing's box side (four bar diameters): later passes read crossings"
                f" seen larger than {lo:g} px from the image shrunk to 0.75, larger than {hi:g} px to 0.5"
            )
    parts.append("`detector.refiner = None`: the first stage alone")
    return "; ".join(parts)


def _int8_passes_lines(model: Path, detector: Detector) -> list[str]:
    """The stage table's row for the int8 copy of the second stage that its later passes read, if it has one."""
    if detector.refiner is None or not detector.refiner.has_int8_passes:
        return []
    path = int8_passes_path(model)
    calibrated = detector.meta.get("refiner", {}).get("int8_calibrated_on", {})
    data = ", ".join(f"`{d}`" for d in calibrated.get("data", [])) or "the training images"
    return [
        f"| second stage, int8 copy | `{path.name}` | {_kib(path)} | (the same) | the passes after the first | "
        f"ONNX Runtime static quantization, calibrated on {calibrated.get('patches', '?')} patches around the "
        f"crossings of {data}; the first pass, whose verification every score counts, stays in float |"
    ]


def _crossing_point_lines(model: Path, detector: Detector, res: dict) -> list[str]:
    """The stage table's row for the crossing-point stage, if the model has one."""
    if detector.crossing_point is None:
        return []
    path = crossing_point_path(model)
    return [
        f"| crossing point | `{path.name}` | {_kib(path)} | {_params(res.get('crossing_point_parameters'))} | "
        f"the {detector.crossing_point.patch_px} px patch around each detection and its viewing ray | the offset "
        "to where the 3D crossing point (the centerlines' midpoint, inside the steel) projects; only when asked "
        '(`detect(rgb, point="crossing")`, `rebar detect --point crossing`); trained on the labels alone |'
    ]


def _line_check_lines(detector: Detector) -> list[str]:
    """The stage table's row for the line check, if the model has one."""
    if detector.line_check is None:
        return []
    e = detector.meta.get("line_check", {})
    fitted = ", ".join(f"`{d}`" for d in e.get("fitted_on", [])) or "its fitting images"
    return [
        "| line check | (weights in the model's metadata) | - | "
        f"{len(detector.line_check.weights) + 1} | without depth: the first-stage scores along each "
        f"detection's two bars (candidates scoring {detector.line_check.floor:g} or more, followed from the "
        "image's edges) | a logistic regression scores again each detection the first stage scores "
        f"{detector.line_check.checked_from:g} or more. Fitted on {e.get('candidates', '?')} candidates of "
        f"{fitted}. `detector.line_check = None`: the RGB stages' scores alone |"
    ]


def _stage_rows(model: Path, detector: Detector, res: dict, tc: dict, *, with_depth: str) -> list[str]:
    """The card's table of model files and stages: file, size, parameters, what it reads, what it does."""
    rows = [
        f"| first stage (heatmap network) | `{model.name}` | {_kib(model)} | {_params(res.get('parameters'))} | "
        "the whole frame and each output cell's viewing ray | a heatmap at stride 4 with a sub-cell offset a cell "
        f"(CenterNet-like), depthwise-separable encoder-decoder, channels {tc['model']['channels']}, blocks "
        f"{tc['model']['blocks']} |"
    ]
    if detector.refiner is not None:
        path = refiner_path(model)
        refine = tc.get("refine") or {}
        rows.append(
            f"| second stage | `{path.name}` | {_kib(path)} | {_params(res.get('refiner_parameters'))} | "
            f"a {refine.get('patch_px', '?')} px full-resolution patch around each detection | "
            f"{_second_stage_cell(refine, detector, with_depth=with_depth)} |"
        )
        rows += _int8_passes_lines(model, detector)
    if detector.depth_check is not None:
        path = depth_check_path(model)
        dc = tc.get("depth_check") or {}
        rows.append(
            f"| depth check | `{path.name}` | {_kib(path)} | {_params(res.get('depth_check_parameters'))} | the "
            f"depth image's {dc.get('patch_px', '?')} px patch (depth relative to its centre, in units of "
            f"{dc.get('scale_m', 0) * 1000:g} mm, clipped to +-{dc.get('clip', 0):g}) | the logit q that the two "
            f"bars there touch; score = sigmoid(logit + {detector.depth_power:g} log q); runs only with a depth "
            "image, and a detection without a measurement at its centre is scored as without depth |"
        )
    rows += _crossing_point_lines(model, detector, res)
    rows += _line_check_lines(detector)
    return [
        "| stage | file | size | parameters | reads | does, as shipped |",
        "| --- | --- | --- | --- | --- | --- |",
        *rows,
    ]


def _lone_crossing_scores(
    detector: Detector, own: Sequence[float] = (0.9, 0.6, 0.5)
) -> list[tuple[float, float]]:
    """What the line check makes of a crossing with no other candidate along its bars: (score in, out)."""
    from rebar_data.perception.inference.checks import features

    check = detector.line_check
    x = features(np.asarray(own, float), np.full((len(own), 2, 1), -1))
    out = 1.0 / (1.0 + np.exp(-(x @ check.weights + check.bias)))
    return list(zip(own, out.tolist(), strict=True))


def _details_lines(model: Path, detector: Detector, res: dict, tc: dict, *, dc: dict | None) -> list[str]:
    """The card's "Model details": what it is, what it takes and gives, its files and stages."""
    stages = ["a first stage that finds candidates on the whole frame"]
    if detector.refiner is not None:
        stages.append(
            "a second that moves each onto the crossing its full-resolution patch shows and verifies it"
        )
    if dc:
        stages.append("a depth check that reads each in the depth image")
    if detector.line_check is not None:
        stages.append("without depth, a line check that weighs each with the detections along its bars")
    with_depth = (
        f"; {detector.verify_power_with_depth:g} log p beside the depth check"
        if dc and detector.verify_power_with_depth != detector.verify_power
        else ""
    )
    return [
        "## Model details",
        "",
        "- Model type: heatmap keypoint detector for one class, the rebar crossing: "
        + "; ".join(stages)
        + ". Trained from scratch on the project's rendered data alone.",
        "- Input: an RGB image of any size (uint8, H x W x 3); optionally its intrinsics (fx, fy, cx, cy in px)"
        + (
            " and its registered depth image (metres, or uint16 millimetres; 0 = no measurement)."
            if dc
            else "."
        ),
        "- Output: (N, 3) u, v, score per crossing, best first, scores >= 0.5; u, v in the image's pixels with",
        "  COCO's corner origin (the top-left corner of the top-left pixel is (0, 0)).",
        "- Label: the sight point, where the image shows the two bars cross (the pixel where their projected",
        "  centerlines cross, on the nearer bar); the crossing's 3D midpoint, inside the steel, lies a bar radius",
        "  deeper.",
        "- Runs on: numpy, OpenCV and ONNX Runtime (OpenVINO where installed); no PyTorch.",
        f"- License: none declared yet (`license: {LICENSE}` in the header).",
        f"- Design of each stage: [{DESIGN_DOC}]({DOCS_FROM_CARD}/design.md); every setting tried, adopted or",
        f"  not, with its figures: [{EXPERIMENTS_DOC}]({DOCS_FROM_CARD}/experiments.md).",
        "",
        "### Files and stages",
        "",
        *_stage_rows(model, detector, res, tc, with_depth=with_depth),
        "",
        f"- Operating threshold: score 0.5, placed at the best F1 on the val split (a logit shift of "
        f"{detector.score_bias:+.2f} stored in the file; it changes no ranking, so AP and recall at a precision"
        " do not depend on it)"
        + (
            f"; without a depth image the RGB stages' own, placed the same way ({detector.score_bias_without_depth:+.2f})."
            if dc
            else "."
        ),
        *_reading_lines(detector),
        *_focal_lines(detector),
        "",
    ]


def _reading_lines(detector: Detector) -> list[str]:
    """How the card's figures read each image (:mod:`rebar_data.perception.inference.detector`)."""
    how = (
        "mirrored: the first stage reads the image and its mirror image and takes their mean, the second stage "
        "reads its int8 copy, its later passes in one view"
        if detector.reading == "mirrored"
        else "once, the second stage's first pass in float (the single reading)"
    )
    return [
        f"- Reading: the figures on this card read each image {how}; `Detector.load` reads mirrored by default,",
        '  `reading="single"` once.',
    ]


def _focal_lines(detector: Detector) -> list[str]:
    """At what focal length the detector reads a frame (:mod:`rebar_data.perception.inference.image`)."""
    if detector.focal_px is None:
        return []
    return [
        f"- Camera: trained on frames of focal length {detector.focal_px:g} px. `detect` reads a frame whose focal",
        f"  length differs by more than {TOLERANCE:.0%} resized to {detector.focal_px:g} px and answers in its own"
        " pixels (without intrinsics a frame of any size is taken to have the training camera's field of view);",
        "  `detector.resample = False` reads every frame at its own scale.",
    ]


def _use_lines(ds: dict, detector: Detector, *, dc: dict | None, rgb_path: str) -> list[str]:
    """The card's "Intended use and limits"."""
    lone = (
        [
            "- The line check learned from whole mats seen by the camera. A crossing with no other candidate along",
            "  its bars (a lone crossing, two bars in view) is scored from its own score alone: "
            + ", ".join(f"{a:g} becomes {b:.3f}" for a, b in _lone_crossing_scores(detector))
            + "; a crossing among many doubtful ones along both its bars is scored down.",
        ]
        if detector.line_check is not None
        else []
    )
    return [
        "## Intended use and limits",
        "",
        "**Intended use.** Finding rebar crossings, sub-pixel, in the frames of a robot's camera looking at a",
        "reinforcement mat (tunnel segments and planar slabs like the training pipelines'), so that a tying tool can",
        "be servoed onto them; on a CPU, in a closed loop (`rebar servo run`). Also: scoring rendered datasets",
        "(`rebar detect DATASET`) and as the baseline a retrained model is compared with.",
        "",
        "**Out of scope.**",
        "- Real photographs as a measured use: no real photograph was seen in training or scored here.",
        "- Other keypoints (bar ends, ties, bar axes) and other objects; lenses that are not pinhole (fisheye).",
        *(
            [
                "- Depth images of bars lying directly on a surface: the depth check doubts every crossing there;"
                " give such images no depth."
            ]
            if dc
            else []
        ),
        "- Any use that needs its detections without a check: a false detection places the tool on no crossing.",
        "",
        "**Known limits.**",
        "- Trained and scored on rendered images only (the renderers under Training data).",
        *(
            [
                "- One mesh (the paper's tunnel segment, 12 mm bars at 100 mm) and one focal length in training; the",
                "  other-config rows of the evaluation say how far that carries.",
            ]
            if len(ds.get("supplements") or []) <= 1
            else [
                "- The meshes, bars, cameras and looks trained on are those of the pipelines named under Training",
                "  data; the other-config rows (never trained on) and the other renderer's rows say how far they carry.",
            ]
        ),
        *(
            [
                "- The depth check learned from mats with open space behind their bars (the element's far face, the",
                "  mat beneath or the surroundings); bars lying directly on a surface are outside what it saw.",
                f"- Without depth ({rgb_path}) the confident false detections left are mostly places where a top bar",
                "  passes in front of a lower mat's bar: compare the evaluation's `without depth` / `RGB only` rows",
                "  with the `with depth` ones.",
            ]
            if dc
            else []
        ),
        *lone,
        "",
    ]


def _training_lines(
    res: dict, tc: dict, ds: dict, *, refine: dict | None, dc: dict | None, figure: str | None
) -> list[str]:
    """The card's "Training data" (and how it was trained): every figure from the run's records."""
    verifies = bool(refine and refine.get("verify"))
    lines = [
        "## Training data",
        "",
        f"- Data: `{ds.get('name')}` v{ds.get('version')}, its train split (early stopping and the choice of",
        "  epoch on val); the dataset is split by scene, so no frame of a val or test scene was trained on.",
        *_supplement_lines(ds.get("supplements") or []),
        _renderer_line(ds),
        f"- Occluded crossings (visibility 1): {tc['occluded']} in the loss.",
        "",
        "**Training procedure.**",
        f"- {res['epochs_run']} epochs run, best at epoch {res['best_epoch']}"
        + (" (stopped early)" if res["stopped_early"] else "")
        + f", {res['train_seconds_total'] / 60:.1f} minutes of training on this 2-core CPU"
        + f" (network threads: {tc['threads']}; batches made in a second process).",
        f"- Crops of {tc['crop_px']} px ({tc['crops_per_image']} a training image an epoch), batch {tc['batch_size']},",
        f"  AdamW lr {tc['lr']:g} (warm-up, cosine), weight average; "
        + (
            f"mosaic for the first {tc['augment']['mosaic_epochs']} epochs then off (as the paper);"
            if tc["augment"]["mosaic_epochs"]
            else "no mosaic (it would mix four perspectives in one crop);"
        ),
        f"  scale {tc['augment']['scale']}, rotation +-{tc['augment']['rotation_deg']:g} deg and flips (the viewing rays"
        " turn with the crop), colour, gamma, blur, noise"
        + (
            f"; the hue turned anywhere for {tc['augment']['hue_full_probability']:.0%} of the crops (coatings such as"
            f" epoxy green), white balance +-{tc['augment']['white_balance']:.0%} a channel."
            if tc["augment"].get("hue_full_probability") or tc["augment"].get("white_balance")
            else "."
        ),
        *_distractor_gain_lines(tc["augment"]),
        *_adapt_lines(res, tc, ds),
    ]
    if refine:
        lines += [
            f"- Second stage: {refine['epochs']} epochs over the training split's visible crossings "
            f"({res.get('refine_seconds', 0.0) / 60:.1f} minutes, in the total above),",
            f"  each a {refine['patch_px']} px patch centred with a random error (Gaussian sigma "
            f"{refine['jitter_px']:g} px, or for {refine['jitter_uniform_fraction']:.0%} uniform up to "
            f"{refine['jitter_uniform_px']:g} px), turned, flipped, scaled and recoloured like the crops; smooth-L1 loss",
            "  on the offset, learnt from the labels alone.",
        ]
        if refine.get("border", "mirror") == "mask":
            lines.append(
                f"  {refine['border_fraction']:.0%} of the patches get a border of their own, a straight edge within "
                f"{refine['border_reach_px']:g} px of the crossing, beyond which the patch is blank."
            )
        if verifies:
            lines += [
                f"  Its verification also learns from negatives: the trained first stage's detections (score >= "
                f"{refine['negative_score']:g})",
                f"  on the training images farther than {refine['negative_gate_px']:g} px from every "
                "visible crossing; cross-entropy beside the offset loss.",
            ]
            if refine.get("lower_mat_negatives"):
                lines.append(
                    f"  With them, up to {refine['lower_mat_negatives']} of the crossings each image's lower "
                    "mat shows (its own, and top bars in front of its bars; placed from the tables)."
                )
        lines += _refine_supplement_lines(
            ds.get("refine_supplements") or [],
            refine,
            bool(res.get("adapt_epochs")),
            tc.get("other_renderer_repeats", 0),
        )
    if dc:
        lines += [
            f"- Depth check: {dc['epochs']} epochs over depth patches around the training images' visible crossings and",
            f"  the second stage's negatives ({res.get('depth_check_seconds', 0.0) / 60:.1f} minutes, in the total above), "
            f"centred with a Gaussian error of {dc['jitter_px']:g} px,",
            f"  turned by quarter turns, flipped, the relative depth scaled by {dc['gain'][0]:g}-{dc['gain'][1]:g}; cross-entropy.",
        ]
        if dc.get("lower_mat_negatives"):
            lines.append(
                f"  Its negatives also hold up to {dc['lower_mat_negatives']} of the crossings each image's lower "
                "mat shows (its own, and top bars in front of its bars; placed from the tables)."
            )
    if res.get("crossing_point_history"):
        cp = tc.get("crossing_point") or {}
        lines.append(
            f"- Crossing-point stage: {len(res['crossing_point_history'])} epochs "
            f"({res.get('crossing_point_seconds', 0.0) / 60:.1f} minutes, in the total above), {cp.get('patch_px', '?')} px"
            " patches, on the labels' 3D crossing points."
        )
    lines += [
        "- Reproduce: `make train` (builds the default dataset, its supplements and the planar-slab set when",
        "  missing, trains with `TrainConfig`'s defaults, and ships this file, its card and the card's figures);",
        "  the settings this run resolved are listed below; what was tried, adopted or not, with its figures:",
        f"  [experiments.md]({DOCS_FROM_CARD}/experiments.md).",
        "",
        *(
            [f"![Training curves of this run]({figure})", ""]
            if figure
            else ["(No training curves: the run folder had no `metrics.csv`.)", ""]
        ),
        "<details><summary>Settings (<code>TrainConfig</code>, as this run resolved them)</summary>",
        "",
        "```json",
        "{",
        *(
            f' "{k}": {json.dumps(v, sort_keys=True)}{"," if i < len(tc) - 1 else ""}'
            for i, (k, v) in enumerate(sorted(tc.items()))
        ),
        "}",
        "```",
        "",
        "</details>",
        "",
    ]
    return lines


def _row_parts(name: str, default_input: str) -> tuple[str, str]:
    """A row name split into its held-out set and its input (mode, and the part of the set when a row holds
    one): ``"crossval-planar v1.1.0, cycles renderer, RGB only"`` -> the set and ``"cycles renderer, RGB only"``.
    A row that names no input read the detector's default one (``default_input``)."""
    head, _, rest = name.partition(", ")
    if not rest:
        return head, default_input
    if any(w in rest for w in ("depth", "RGB", "first stage alone")):
        return head, rest
    return head, f"{default_input}; {rest}"


def _headline(head: str, rest: str, default_input: str) -> bool:
    """Whether a row is one set as read in one mode (the model index's entries), not a part of a set, the
    val split or frames that were trained on."""
    if head.endswith(" val") or " random " in head:
        return False
    return (
        rest in (default_input, "RGB only", "with depth")
        or rest.startswith("without depth (")
        or rest.endswith(("renderer, RGB only", "renderer, with depth"))
    )


def _table_row(head: str, rest: str, m: dict) -> str:
    return (
        f"| {head} | {rest} | {int(m['n_gt'])} | {m['oks_ap50']:.4f} | {m['oks_ap']:.4f} | {m['pck1']:.3f} | "
        f"{m['pck2']:.3f} | {m['pck5']:.3f} | {m['mean_px']:.2f} | {m['median_px']:.2f} | {m['precision']:.3f} | "
        f"{m['recall']:.3f} | {m['recall_at_p99']:.3f} |"
    )


def _grouped(rows: dict[str, dict], default_input: str) -> list[tuple[str, str, dict]]:
    """(set, input, metrics) of every row, each set's rows together, sets in the order they first appear."""
    groups: dict[str, list[tuple[str, str, dict]]] = {}
    for name, m in rows.items():
        head, rest = _row_parts(name, default_input)
        groups.setdefault(head, []).append((head, rest, m))
    return [r for g in groups.values() for r in g]


MODEL_INDEX_METRICS = {  # summary key -> the model index's metric type and name
    "oks_ap50": ("oks_ap50", "OKS AP@0.5"),
    "oks_ap": ("oks_ap", "OKS AP@0.5:0.95"),
    "pck2": ("pck2", "PCK@2px"),
    "median_px": ("median_px", "median error (px)"),
    "recall_at_p99": ("recall_at_p99", "recall at precision 0.99"),
}


def header(rows: list[tuple[str, str, dict]], ds: dict, *, default_input: str) -> dict:
    """The card's YAML metadata as the Hugging Face Hub reads it: license, library, tags, task, the training
    datasets and the model index (each held-out set in each input mode, with its headline figures)."""
    datasets = [ds.get("name")] + [
        d.get("name") for d in (ds.get("supplements") or []) + (ds.get("refine_supplements") or [])
    ]
    results = []
    for head, rest, m in rows:
        if not _headline(head, rest, default_input):
            continue
        name = head.split(" (")[0]
        split = name.rsplit(" ", 1)[1] if name.endswith((" test", " val")) else "all"
        results.append(
            {
                "task": {"type": "keypoint-detection", "name": "Rebar crossing detection"},
                "dataset": {"name": f"{head}, {rest}", "type": name.split(" ")[0], "split": split},
                "metrics": [
                    {"type": t, "name": n, "value": round(float(m[k]), 4)}
                    for k, (t, n) in MODEL_INDEX_METRICS.items()
                    if np.isfinite(
                        m[k]
                    )  # a median error with no match is NaN: the table shows it, the index not
                ],
            }
        )
    return {
        "license": LICENSE,
        "license_name": LICENSE_NAME,
        "library_name": "onnx",
        "pipeline_tag": "keypoint-detection",
        "tags": [
            "keypoint-detection",
            "rebar",
            "construction",
            "robotics",
            "visual-servoing",
            "synthetic-data",
            "onnx",
        ],
        "datasets": list(dict.fromkeys(d for d in datasets if d)),
        "model-index": [{"name": MODEL_NAME, "results": results}],
    }


def _evaluation_lines(
    grouped: list[tuple[str, str, dict]],
    rows: dict[str, dict],
    ds: dict,
    *,
    sigma: float,
    dc: dict | None,
    refine: dict | None,
    rgb_path: str,
    figures: dict[str, str],
) -> list[str]:
    """The card's "Evaluation": how it scores, the one table, the PR curves and what each row is."""
    verifies = bool(refine and refine.get("verify"))
    return [
        "## Evaluation",
        "",
        f"OKS sigma {sigma:g}; object area = the crossing's square box (side `box_size_px`, four projected bar",
        f"diameters), so OKS 0.5 is reached at {oks_radius_px(sigma, 25):.1f} px for a 25 px box and "
        f"{oks_radius_px(sigma, 40):.1f} px for a 40 px box (the paper-tunnel median). AP is COCOeval's (101 recall",
        "thresholds; each above the recall reached with every detection counts precision 0, so where more than one",
        "crossing in a hundred is never found within OKS 0.5, AP@0.5 stays under 0.99: at recall 0.988, at most",
        "0.980; `rebar detect` prints that recall and the ceiling, `metrics.ap_ceiling`). PCK, errors, P and R:",
        "Hungarian matching per image with a 5 px gate, detections of score >= 0.5; R@P0.99: the best recall along",
        "the score-sorted detections while precision >= 0.99. Visible crossings only (visibility 2).",
        "",
        "| held-out set | input | crossings | AP@0.5 | AP@0.5:0.95 | PCK@1px | PCK@2px | PCK@5px | mean px | median px | P | R | R@P0.99 |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *(_table_row(h, r, m) for h, r, m in grouped),
        "",
        *(
            [
                "Precision against recall at OKS 0.5, one figure a held-out set (dots: score 0.5; dotted: precision 0.99):",
                "",
                " ".join(f"![PR curve: {label}]({path})" for label, path in figures.items()),
                "",
            ]
            if figures
            else []
        ),
        f"- `{ds.get('name')} test`: the held-out scenes (other lights, materials, surroundings and camera paths);",
        "  the figure to quote. `val`: the scenes that chose the epoch.",
        *_row_notes(rows, verifies=verifies, rgb_path=rgb_path),
        *_census_lines(rows),
        "",
    ]


def _row_notes(rows: dict[str, dict], *, verifies: bool, rgb_path: str) -> list[str]:
    """What the table's row names mean, for the names it holds."""
    notes = {
        "px inside the frame": [
            f"- `crossings >= {BORDER_BAND_PX:g} px inside the frame`: the crossings within {BORDER_BAND_PX:g} px of"
            " the image border set aside (ignore regions), and the detections there.",
        ],
        "lower mat": [
            "- `scenes with (without) a lower mat`: the scenes with a second mat beneath the bars (the samples",
            f"  table's `{LOWER_MAT_COLUMN}`), where a bar passing over the mat beneath looks like a crossing.",
        ],
        " random ": [
            "- `random ... of frames`: frames drawn at random from the whole dataset, as the paper's frame-level",
            "  80:20 split draws its test set; most were trained on: the gap to the test row is what it hides.",
        ],
        "(all splits)": [
            "- `(all splits)`: datasets built with other configs (`pipelines/*.yaml`), never trained on."
        ],
        "renderer": [
            "- `cycles renderer`: sets rendered by Blender Cycles, never trained on; a user's camera stand-in."
        ],
        "regression gate": [
            "- `(the regression gate's set)`: `pipelines/detector-gate.yaml`, 120 held-out scenes that `make test`",
            "  scores the shipped model on (`gate.json` beside this card holds its floors).",
        ],
        "first stage alone": [
            "- `first stage alone`: the heatmap network's detections without the later stages"
            + (" (before verification)." if verifies else "."),
        ],
        "depth": [
            "- `with depth`: each image's depth image given, as the robot's RGB-D camera does. `without depth`,",
            f"  `RGB only`: {rgb_path.replace('the RGB', 'the two RGB')}, at their own operating point, as for photographs.",
        ],
        "without the line check": [
            "- `without the line check`: the RGB stages alone, without the line check."
        ],
        FLATTENED: [
            f"- `{FLATTENED}`: every pixel more than {GAP_M:g} m behind the nearest surface around it first",
            "  replaced by the blurred colour of such pixels nearby (`Detector.flatten_behind`, off by default).",
        ],
        "vs 3D crossing points": [
            "- `vs 3D crossing points`: scored against where the crossings' 3D points project instead of the",
            "  labels' sight points; `crossing points vs ...`: with the crossing-point stage's output.",
        ],
    }
    return [line for marker, lines in notes.items() if any(marker in name for name in rows) for line in lines]


def _how_to_use_lines(*, dc: dict | None) -> list[str]:
    return [
        "## How to use",
        "",
        "```python",
        "from rebar_data.perception import Detector",
        "",  # the block as `ruff format` (which formats code in Markdown) leaves it
        "detector = Detector.load()  # this model; runtime=, reading= as `rebar detect`'s flags",
        "uvs = detector.detect(rgb, camera=(fx, fy, cx, cy))  # (N, 3): u, v, score >= 0.5",
        *(
            ["uvs = detector.detect(rgb, camera=(fx, fy, cx, cy), depth=depth)  # registered depth"]
            if dc
            else []
        ),
        "```",
        "",
        "Pass the camera's intrinsics: the network reads each output cell's viewing ray (without them it assumes",
        "the principal point at the centre and the training camera's field of view).",
        "",
        "```bash",
        "rebar detect IMAGE_OR_FOLDER --out DIR                           # overlays and cameras.json",
        "rebar detect DATASET --split test --out pred.parquet --metrics m.json   # one row a detection, and its scores",
        "make train                                                       # retrain and ship this file and card",
        "```",
        "",
        "The README's detector section lists every flag; `rebar adapt` trains the first stage further on your",
        "camera's labelled frames.",
        "",
    ]


def _latency_lines(
    latency: DetectorLatency, latency_source: str, latency_runtime: str, load: str
) -> list[str]:
    return [
        "## Latency",
        "",
        f"- {latency.median_ms:.1f} ms a 640x480 frame, batch 1, 2 CPU threads, {latency_runtime}, end to end",
        f"  (median, measured when shipped{load}, over {latency_source}: {latency.candidates:.0f} candidates",
        f"  and {latency.crossings:.0f} crossings found a frame on average"
        + (
            f"; the first stage alone {latency.first_stage_ms:.1f} ms, so the later stages cost "
            f"{latency.second_stage_us_per_candidate:.0f} us a candidate"
            if latency.first_stage_ms is not None
            else ""
        )
        + ").",
        "- `rebar bench --only detector` measures it again beside a YOLOv8n-pose-shaped network. The figures",
        "  above are ONNX Runtime's in float32, the runtime training fits on; `Detector.load` runs OpenVINO in",
        '  bfloat16 where the CPU has it (`runtime="auto"`), which moves them by a few detections.',
        "",
    ]


def write_card(
    run_dir: Path,
    path: Path,
    *,
    model: Path,
    latency: DetectorLatency,
    latency_source: str,
    extra_results: dict[str, dict] | None = None,
    load_average: float | None = None,
    detector: Detector,
    latency_runtime: str = "ONNX Runtime, float32",
    figures: CardFigures | None = None,
) -> Path:
    """The model card in the Hugging Face Hub's form: a YAML header (license, library, tags, task, datasets,
    the model index), then model details, intended use and limits, training data, evaluation, how to use and
    latency. ``detector`` is ``model`` loaded: its stages, score biases and powers are what the card states;
    its figures are ONNX Runtime's in float32, and the latency was measured with ``latency_runtime``.
    ``figures`` are the PNGs :func:`write_figures` wrote, linked relative to the card."""
    figures = figures or CardFigures()
    res = json.loads((run_dir / "results.json").read_text())
    cfg = json.loads((run_dir / "config.json").read_text())
    tc = cfg["train_config"]
    sigma = res["oks_sigma"]
    ds = res["dataset"]
    rgb_path = (
        "the RGB stages and the line check" if detector.line_check is not None else "the RGB stages alone"
    )
    refine = tc.get("refine") if detector.refiner is not None else None
    dc = tc.get("depth_check") if detector.depth_check is not None else None
    default_input = "with depth" if dc else "RGB"
    rows = {f"{ds.get('name')} {split}": m for split, m in sorted(res["results"].items(), reverse=True)}
    rows |= {
        f"{ds.get('name')} {split}, without depth ({rgb_path})": m
        for split, m in sorted(res.get("results_without_depth", {}).items())
    }
    rows |= {
        f"{ds.get('name')} {split}, first stage alone": m
        for split, m in sorted(res.get("results_first_stage", {}).items())
    }
    rows |= extra_results or {}
    grouped = _grouped(rows, default_input)
    load = (
        f", load average {load_average:.1f} on this machine ({machine_description()})"
        if load_average is not None
        else ""
    )
    test = rows.get(f"{ds.get('name')} test")
    lines = [
        "---",
        yaml.safe_dump(
            header(grouped, ds, default_input=default_input),
            sort_keys=False,
            width=110,
            default_flow_style=None,  # lists and maps of plain values on one line each
        ).rstrip(),
        "---",
        "",
        "# Rebar-crossing keypoint detector",
        "",
        "Finds the crossings of a rebar mat in a camera frame, sub-pixel, on a CPU: a heatmap network and patch",
        "stages trained from scratch on the project's rendered images"
        + (
            f"; on held-out rendered scenes {default_input}, AP@0.5 {test['oks_ap50']:.3f}, PCK@2px "
            f"{test['pck2']:.3f}, recall at precision 0.99 {test['recall_at_p99']:.3f}."
            if test
            else "."
        ),
        "",
        *(
            [f"![One frame with its detections]({figures.frame})", "", f"*{figures.frame_caption}*", ""]
            if figures.frame
            else []
        ),
        *_details_lines(model, detector, res, tc, dc=dc),
        *_use_lines(ds, detector, dc=dc, rgb_path=rgb_path),
        *_training_lines(res, tc, ds, refine=refine, dc=dc, figure=figures.training),
        *_evaluation_lines(
            grouped, rows, ds, sigma=sigma, dc=dc, refine=refine, rgb_path=rgb_path, figures=figures.pr
        ),
        *_how_to_use_lines(dc=dc),
        *_latency_lines(latency, latency_source, latency_runtime, load),
    ]
    path.write_text("\n".join(lines))
    return path


def _census_lines(rows: dict[str, dict]) -> list[str]:
    """The card's words on where the confident false detections of the rows that counted them lie."""
    counted = [(name, m["false_detections"]) for name, m in rows.items() if m.get("false_detections")]
    if not counted:
        return []
    from rebar_data.perception.evaluation.false_detections import format_census

    return [
        f"- Where the confident false detections lie (above the score where recall reaches "
        f"{counted[0][1]['recall']:g}; `rebar detect` on a dataset counts them so):",
        *(f"  - `{name}`: {format_census(c)}." for name, c in counted),
    ]


def _flattened_predictions(detector: Detector, samples: Sequence, *, progress: bool) -> list | None:
    """The detections with each sample's depth image and what lies behind the bars in front flattened
    (``Detector.flatten_behind``, :mod:`~rebar_data.perception.inference.image`), or None when the detector has no
    depth check or a sample has no depth image. The detector's setting is left as it was."""
    if detector.depth_check is None or not samples or any(s.depth_path is None for s in samples):
        return None
    with detector.flattening():
        return predict(detector, samples, progress=progress)


def evaluation_rows(
    detector: Detector,
    run_dir: Path,
    *,
    evaluate_on: Sequence[str | Path] = (),
    random_split: bool = True,
    progress: bool = False,
    held_out: dict[str, HeldOut] | None = None,
) -> dict[str, dict]:
    """The card's rows beyond the run's own splits: where the test split's errors lie
    (:func:`~rebar_data.perception.evaluation.evaluate.breakdown`), the training dataset scored as a random frame
    split would test it, and every split of each dataset in ``evaluate_on`` (datasets built with other
    configs). ``held_out``, when given, receives each held-out set's detections per input mode (set name ->
    :class:`HeldOut`), for the card's figures.

    Returns:
        Row name -> metrics (as :func:`rebar_data.perception.evaluation.metrics.summary` gives them).
    """
    from rebar_data.perception.evaluation.evaluate import (
        RANDOM_SPLIT_FRACTION,
        breakdown,
        load_splits,
        random_frames,
        score,
    )
    from rebar_data.perception.evaluation.false_detections import false_detection_census

    res = json.loads((run_dir / "results.json").read_text())
    rows: dict[str, dict] = {}
    held_out = {} if held_out is None else held_out
    default_input = "with depth" if detector.depth_check is not None else "RGB"
    root = Path(res["dataset"].get("path") or "")
    test = load_split(root, "test") if (root / "tables/samples.parquet").exists() else []
    if test:
        preds = predict(detector, test, progress=progress)
        seen = held_out.setdefault(f"{res['dataset'].get('name')} test", HeldOut(test, res["oks_sigma"]))
        seen.modes[default_input if any(s.depth_path is not None for s in test) else "RGB"] = preds
        for name, m in breakdown(root, test, preds, sigma=res["oks_sigma"]).items():
            rows[f"{res['dataset'].get('name')} test, {name}"] = m
        if detector.depth_check is not None and any(s.depth_path is not None for s in test):
            # from RGB alone as well, split by scene: where the RGB path's errors lie
            rgb = predict(detector, test, depth=False, progress=progress)
            seen.modes["RGB only"] = rgb
            for name, m in breakdown(root, test, rgb, sigma=res["oks_sigma"]).items():
                if name.startswith("scenes"):
                    rows[f"{res['dataset'].get('name')} test, without depth, {name}"] = m
        flat = _flattened_predictions(detector, test, progress=progress)
        if flat is not None:
            rows[f"{res['dataset'].get('name')} test, {FLATTENED}"] = score(
                test, flat, sigma=res["oks_sigma"]
            )
    if random_split and (root / "tables/samples.parquet").exists():
        samples, seen = random_frames(root)
        preds = predict(detector, samples, progress=progress)
        name = (
            f"{res['dataset'].get('name')} random {RANDOM_SPLIT_FRACTION:.0%} of frames "
            f"({seen} of {len(samples)} trained on)"
        )
        rows[name] = score(samples, preds, sigma=res["oks_sigma"])
    for path in evaluate_on:
        path = check_dataset(path)
        info = read_info(path)
        label = f"{info.get('name') or path.parent.name} v{info.get('version', '?')}"
        engine = renderer_engine(info)
        if engine == "open3d":
            samples = load_splits(path)
            preds = predict(detector, samples, progress=progress)
            rows[f"{label} (all splits)"] = score(samples, preds, sigma=stated_oks_sigma(path))
            with_depth = detector.depth_check is not None and any(s.depth_path is not None for s in samples)
            held_out[f"{label} (all splits)"] = HeldOut(
                samples, stated_oks_sigma(path), {"with depth" if with_depth else "RGB": preds}
            )
            continue
        # another renderer's images stand for a user's camera: scored from RGB alone, against the labels
        # and against the projected 3D crossing points (what labels made from the 3D point alone expect)
        sigma = stated_oks_sigma(path)
        samples = load_splits(path)
        preds = predict(detector, samples, depth=False, progress=progress)
        seen = held_out.setdefault(f"{label}, {engine} renderer", HeldOut(samples, sigma))
        seen.modes["RGB only"] = preds
        rows[f"{label}, {engine} renderer, RGB only"] = {
            **score(samples, preds, sigma=sigma),
            "false_detections": false_detection_census(path, samples, preds),
        }
        for name, m in breakdown(path, samples, preds, sigma=sigma).items():
            if name.startswith("scenes"):  # where its misses and false detections lie
                rows[f"{label}, {engine} renderer, RGB only, {name}"] = m
        flat = _flattened_predictions(detector, samples, progress=progress)
        if flat is not None:
            # the same frames with their depth images, as an RGB-D camera gives them, and flattened behind
            seen.modes["with depth"] = predict(detector, samples, progress=progress)
            rows[f"{label}, {engine} renderer, with depth"] = score(
                samples, seen.modes["with depth"], sigma=sigma
            )
            rows[f"{label}, {engine} renderer, with depth, {FLATTENED}"] = score(samples, flat, sigma=sigma)
        crossing = load_splits(path, truth="crossing")
        rows[f"{label}, {engine} renderer, RGB only, vs 3D crossing points"] = score(
            crossing, preds, sigma=sigma
        )
        if detector.crossing_point is not None:  # the same, with the crossing-point stage's output
            found = at_crossing_points(detector, samples, preds)
            rows[f"{label}, {engine} renderer, RGB only, crossing points vs 3D crossing points"] = score(
                crossing, found, sigma=sigma
            )
    return rows


def ship(
    run_dir: str | Path,
    *,
    models_dir: Path = MODELS_DIR,
    extra_results: dict[str, dict] | None = None,
    evaluate_on: Sequence[str | Path] = (),
    random_split: bool = True,
    progress: bool = False,
    gate: bool = True,
) -> Path:
    """Copy a run's ``best.onnx`` into the package as the shipped model and write its card.

    Args:
        run_dir: A finished training run folder.
        models_dir: Where shipped models live.
        extra_results: More rows for the card's table, name -> metrics.
        evaluate_on: Datasets built with other configs, scored over all their splits for the card.
        random_split: Also score the training dataset on frames drawn at random, as a random split would.
        progress: Show progress bars while scoring.
        gate: Also write the regression gate's reference figures beside the model (``gate.json``, with rows
            in the card; :mod:`~rebar_data.perception.evaluation.gate`, about a minute); False removes a stale one.

    Returns:
        The shipped model file.
    """
    run_dir = Path(run_dir)
    src = run_dir / "best.onnx"
    if not src.exists() or not (run_dir / "results.json").exists():
        raise ConfigError(
            f"{run_dir}: no best.onnx and results.json; accepted: a finished `rebar train` run folder"
        )
    size = sum(p.stat().st_size for p in (src, *stage_files(src)) if p.exists())
    if size > MAX_SHIPPED_BYTES:
        raise ConfigError(
            f"{src}: {size / 2**20:.1f} MiB (with its later stages) is over the "
            f"{MAX_SHIPPED_BYTES / 2**20:.0f} MiB a shipped model may take"
        )
    for path in evaluate_on:
        check_dataset(path)  # a wrong path fails before anything is copied
    models_dir.mkdir(parents=True, exist_ok=True)
    dst = models_dir / SHIPPED_MODEL.name
    pairs = [(src, dst)]
    for a, b in zip(stage_files(src), stage_files(dst), strict=True):
        if a.exists():
            pairs.append((a, b))
        else:
            b.unlink(missing_ok=True)  # a model without that stage: no stale file beside it
    for a, b in pairs:
        shutil.copyfile(a, b.with_name(b.name + ".tmp"))
    for _, b in reversed(pairs):  # the later stages land first, so the first never names a missing file
        b.with_name(b.name + ".tmp").replace(b)
    detector = Detector.load(dst, runtime="onnxruntime")  # the card's figures: float32, as trained
    held_out: dict[str, HeldOut] = {}
    rows = evaluation_rows(
        detector,
        run_dir,
        evaluate_on=evaluate_on,
        random_split=random_split,
        progress=progress,
        held_out=held_out,
    )
    rows.update(extra_results or {})
    if gate:
        rows.update(_gate_rows(detector, dst, models_dir, held_out))
    else:
        from rebar_data.perception.evaluation.gate import GATE_NAME

        (models_dir / GATE_NAME).unlink(missing_ok=True)
    test = f"{json.loads((run_dir / 'results.json').read_text())['dataset'].get('name')} test"
    figures = write_figures(run_dir, models_dir, held_out, frame_from=test if test in held_out else None)
    load = os.getloadavg()[0]
    frames, latency_source = latency_frames()
    fast = Detector.load(dst)  # what a caller's detector runs: the default runtime
    latency = detector_latency(fast, frames, repeats=64)
    write_card(
        run_dir,
        models_dir / CARD_NAME,
        model=dst,
        latency=latency,
        latency_source=latency_source,
        extra_results=rows,
        load_average=load,
        detector=detector,
        latency_runtime=runtime_description(fast.backend),
        figures=figures,
    )
    return dst


def _gate_rows(
    detector: Detector, model: Path, models_dir: Path, held_out: dict[str, HeldOut]
) -> dict[str, dict]:
    """Write the regression gate's reference for ``model`` (``gate.json``) and return its card rows; the gate
    set's detections per mode go into ``held_out`` for its PR figure."""
    from rebar_data.perception.evaluation.gate import (
        GATE_NAME,
        MODE_NAMES,
        build_gate_set,
        card_rows,
        gate_predictions,
        load_gate_set,
        write_reference,
    )

    with tempfile.TemporaryDirectory(prefix="rebar-gate-") as tmp:
        root = build_gate_set(tmp)
        path = write_reference(model, out=models_dir / GATE_NAME, data_root=tmp)
        samples, _ = load_gate_set(root)
        preds = gate_predictions(detector, samples)
        rows = card_rows(path)
        name = next(iter(rows)).rsplit(", ", 1)[0]
        held_out[name] = HeldOut(
            samples, stated_oks_sigma(root), {MODE_NAMES[m]: p for m, p in preds.items()}
        )
    return rows
