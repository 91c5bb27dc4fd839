"""Ship a trained model with the package: its ONNX file and a model card written from the run's own records."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

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
from rebar_data.perception.inference.detector import DUPLICATE_PX, MODELS_DIR, SHIPPED_MODEL, Detector
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


def _crossing_point_lines(model: Path, detector: Detector, res: dict) -> list[str]:
    """The card's words on the crossing-point stage, if the model has one."""
    if detector.crossing_point is None:
        return []
    path = crossing_point_path(model)
    params = res.get("crossing_point_parameters")
    size = f"{path.stat().st_size / 1024:.0f} KiB" + (f", {params / 1e3:.0f} k parameters" if params else "")
    return [
        f"- Crossing-point stage: `{path.name}` (ONNX, {size}), beside the first. It reads the",
        f"  {detector.crossing_point.patch_px} px patch around each detection with its viewing ray and gives the offset to where",
        "  the 3D crossing point (the centerlines' midpoint, inside the steel) projects; used only when asked",
        '  (`detect(rgb, point="crossing")`, `rebar detect --point crossing`). Trained on the labels alone.',
    ]


def _int8_passes_lines(model: Path, detector: Detector) -> list[str]:
    """The card's line on the int8 copy of the second stage that its later passes read, when it has one."""
    if detector.refiner is None or not detector.refiner.has_int8_passes:
        return []
    entry = detector.meta.get("refiner", {})
    path = int8_passes_path(model)
    calibrated = entry.get("int8_calibrated_on", {})
    return [
        f"  The passes after the first read an int8 copy of it, `{path.name}` ({path.stat().st_size / 1024:.0f} KiB;"
        f" ONNX Runtime static quantization, calibrated on {calibrated.get('patches', '?')} patches around the"
        f" crossings of {', '.join(f'`{d}`' for d in calibrated.get('data', [])) or 'the training images'});"
        " the first pass, whose verification every score counts, stays in float.",
    ]


def _line_check_lines(detector: Detector) -> list[str]:
    """The card's words on the line check, if the model has one."""
    if detector.line_check is None:
        return []
    e = detector.meta.get("line_check", {})
    fitted = ", ".join(f"`{d}`" for d in e.get("fitted_on", [])) or "its fitting images"
    return [
        "- Line check (no file: a logistic regression's weights in the model's metadata): without a depth",
        f"  image, every candidate the first stage scores {detector.line_check.floor:g} or more is followed along its two bars",
        "  (their directions read from the image's edges, then candidate to candidate), and each detection",
        f"  the first stage scores {detector.line_check.checked_from:g} or more is scored again from its own score and the scores along",
        "  its bars: a top bar passing in front of a lower mat's bar looks like a crossing, but along the lower",
        f"  bar there are only more such places. Fitted on {e.get('candidates', '?')} candidates of {fitted}; set",
        "  `detector.line_check = None` for the RGB stages' scores alone.",
    ]


def _row(name: str, m: dict) -> str:
    return (
        f"| {name} | {int(m['n_gt'])} | {m['oks_ap50']:.4f} | {m['oks_ap']:.4f} | {m['pck1']:.3f} | {m['pck2']:.3f} | "
        f"{m['pck5']:.3f} | {m['mean_px']:.2f} | {m['median_px']:.2f} | {m['precision']:.3f} | {m['recall']:.3f} | "
        f"{m['recall_at_p99']:.3f} |"
    )


def _reading_lines(detector: Detector) -> list[str]:
    """How the card's figures read each image (:mod:`rebar_data.perception.inference.detector`)."""
    how = (
        "mirrored: the first stage reads the image and its mirror image and takes their mean, the second stage "
        "reads its int8 copy, its later passes in one view"
        if detector.reading == "mirrored"
        else "once, the second stage's first pass in float (the single reading)"
    )
    return [
        f"- Reading: the figures on this card read each image {how}; `Detector.load` reads mirrored by",
        '  default, `reading="single"` once (`rebar_data/perception/inference/detector.py`; the figures of both in',
        "  docs/detector/experiments.md).",
    ]


def _focal_lines(detector: Detector) -> list[str]:
    """At what focal length the detector reads a frame (:mod:`rebar_data.perception.inference.image`)."""
    if detector.focal_px is None:
        return []
    return [
        f"- Camera: trained on frames of focal length {detector.focal_px:g} px. `detect` reads a frame whose focal",
        f"  length differs by more than {TOLERANCE:.0%} resized to {detector.focal_px:g} px and answers in its own pixels",
        "  (pass its intrinsics; without them a frame of any size is taken to have the training camera's field",
        "  of view); `detector.resample = False` reads every frame at its own scale",
        "  (`rebar_data/perception/focal.py`).",
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
) -> Path:
    """The model card: what the model is, what it was trained on, how it scores and how to reproduce it.
    ``detector`` is ``model`` loaded: its stages, score biases and powers are what the card states; its
    figures are ONNX Runtime's in float32, and the latency was measured with ``latency_runtime``."""
    refiner = refiner_path(model) if detector.refiner is not None else None
    depth_check = depth_check_path(model) if detector.depth_check is not None else None
    res = json.loads((run_dir / "results.json").read_text())
    cfg = json.loads((run_dir / "config.json").read_text())
    rgb_path = (
        "the RGB stages and the line check" if detector.line_check is not None else "the RGB stages alone"
    )
    tc = cfg["train_config"]
    sigma = res["oks_sigma"]
    ds = res["dataset"]
    rows = [_row(f"{ds.get('name')} {split}", m) for split, m in sorted(res["results"].items(), reverse=True)]
    rows += [
        _row(f"{ds.get('name')} {split}, without depth ({rgb_path})", m)
        for split, m in sorted(res.get("results_without_depth", {}).items())
    ]
    rows += [
        _row(f"{ds.get('name')} {split}, first stage alone", m)
        for split, m in sorted(res.get("results_first_stage", {}).items())
    ]
    rows += [_row(name, m) for name, m in (extra_results or {}).items()]
    load = (
        f", load average {load_average:.1f} on this machine ({machine_description()})"
        if load_average is not None
        else ""
    )
    refine = tc.get("refine") if refiner is not None else None
    verifies = bool(refine and refine.get("verify"))
    dc = tc.get("depth_check") if depth_check is not None else None
    with_depth = (
        f"; {detector.verify_power_with_depth:g} log p beside the depth check"
        if dc and detector.verify_power_with_depth != detector.verify_power
        else ""
    )
    lines = [
        "# Rebar-crossing keypoint detector",
        "",
        "A heatmap keypoint detector for rebar crossings (CenterNet-like: a heatmap at stride 4 with a",
        "sub-cell offset per cell) on a depthwise-separable encoder-decoder, trained from scratch on the",
        "project's synthetic data alone"
        + (
            ", with a second stage that moves each detection to the crossing its full-resolution patch shows"
            if refine
            else ""
        )
        + (" and a third that checks each one in the depth image." if dc else "."),
        "Input: an RGB image of any size (uint8, H x W x 3) and, optionally, its intrinsics"
        + (" and its registered depth image" if dc else "")
        + ". Output: (u, v,",
        "score) per crossing, in the image's pixels with COCO's corner origin",
        "(the top-left corner of the top-left pixel is (0, 0)).",
        "",
        "```python",
        "from rebar_data.perception import Detector",
        "",  # the block as `ruff format` (which formats code in Markdown) leaves it
        *(
            [
                "# (N, 3): u, v, score >= 0.5; depth: (H, W) metres or uint16 millimetres, 0 = no measurement",
                "uvs = Detector.load().detect(rgb, camera=(fx, fy, cx, cy), depth=depth)",
            ]
            if dc
            else ["uvs = Detector.load().detect(rgb, camera=(fx, fy, cx, cy))  # (N, 3): u, v, score >= 0.5"]
        ),
        "```",
        "",
        "The label it learned is where the image shows the bars crossing: the pixel where the two projected",
        "bar centerlines cross (the dataset's sight point; the crossing's 3D midpoint, inside the steel, lies",
        "a bar radius deeper). The network gets each output cell's viewing ray as a second input, so pass the",
        "camera's intrinsics (without them it assumes the principal point at the centre and the training",
        "camera's focal length for the image's width).",
        "",
        "## Model",
        f"- File: `{model.name}` (ONNX, {model.stat().st_size / 1024:.0f} KiB), "
        f"{cfg['parameters'] / 1e3:.0f} k parameters; channels {tc['model']['channels']}, blocks {tc['model']['blocks']}.",
        *(
            [
                f"- Second stage: `{refiner.name}` (ONNX, "
                f"{'int8, ' if refine.get('quantize', 'none') == 'int8' else ''}"
                f"{refiner.stat().st_size / 1024:.0f} KiB, "
                f"{res.get('refiner_parameters', 0) / 1e3:.0f} k parameters), beside the first; a",
                f"  {refine['patch_px']} px patch around each detection, plain convolutions to 1/8 and two fully",
                "  connected layers regress the crossing's offset from the patch centre"
                + (", and the logit p that the patch shows a" if verifies else "."),
                *(
                    [
                        "  crossing at all. A detection's score becomes sigmoid(first-stage logit + "
                        f"{detector.verify_power:g} log p{with_depth}): the second",
                        "  stage only lowers scores (of bars passing over the mat beneath, mostly).",
                    ]
                    if verifies
                    else []
                ),
                *(
                    [
                        "  Beyond the image's border its patch is blank, with a fourth channel that marks the image, so it",
                        "  can place a crossing whose centre lies just outside the frame; such a detection is dropped.",
                    ]
                    if refine.get("border", "mirror") == "mask"
                    else []
                ),
                *(
                    [
                        f"  It also reads a context view: the {refine['context_scale']} times wider square around each"
                        f" detection, shrunk to {refine['patch_px']} px, as more channels beside the patch.",
                    ]
                    if refine.get("context_scale", 0)
                    else []
                ),
                *(
                    [
                        f"  It reads each patch in {refine['views']} views (turned and flipped, one batch) and places the"
                        " crossing at the mean of their offsets, turned back; the verification is the plain view's."
                        + (
                            f" Its first pass reads {refine['first_pass_views']}"
                            f" view{'s' if refine['first_pass_views'] > 1 else ''}."
                            if refine.get("first_pass_views", refine["views"]) != refine["views"]
                            else ""
                        ),
                    ]
                    if refine.get("views", 1) > 1
                    else []
                ),
                *(
                    [
                        f"  It runs {refine['iterations']} passes: each later one reads the patch centred where the pass"
                        f" before placed the crossing and moves the point {_step(refine)} to where it places it;"
                        f" a detection within {DUPLICATE_PX:g} px of a better one is then dropped.",
                    ]
                    if refine.get("iterations", 1) > 1
                    else []
                ),
                *_int8_passes_lines(model, detector),
                *(
                    [
                        "  Its first pass also gives each crossing's box side (four bar diameters); the later passes"
                        f" read a crossing seen larger than {refine['shrink_above_px'][0]:g} px from the image shrunk"
                        f" to 0.75, larger than {refine['shrink_above_px'][1]:g} px to 0.5, so its patch shows all of it.",
                    ]
                    if refine.get("shrink_above_px") and refine.get("iterations", 1) > 1
                    else []
                ),
                "  `Detector.load` loads both; set `detector.refiner = None` for the first stage alone.",
            ]
            if refine
            else []
        ),
        *(
            [
                f"- Third stage, the depth check: `{depth_check.name}` (ONNX, "
                f"{'int8, ' if dc.get('quantize', 'none') == 'int8' else ''}{depth_check.stat().st_size / 1024:.0f} KiB, "
                f"{res.get('depth_check_parameters', 0) / 1e3:.0f} k parameters), beside the first. It reads the",
                f"  depth image's {dc['patch_px']} px patch around each detection (depth relative to the patch centre's, "
                f"in units of {dc['scale_m'] * 1000:g} mm,",
                f"  clipped to +-{dc['clip']:g}) and gives the logit q that the two bars there touch, as at a crossing; a bar over the mat",
                f"  beneath lies a mat's height behind. The score becomes sigmoid(logit + {detector.depth_power:g} log q). It runs only",
                "  when `detect` gets a depth image; a detection without a measurement at its centre is scored as without",
                "  depth (the RGB stages' score and operating point).",
            ]
            if dc
            else []
        ),
        *_crossing_point_lines(model, detector, res),
        *_line_check_lines(detector),
        f"- Latency: {latency.median_ms:.1f} ms a 640x480 frame, batch 1, 2 CPU threads, {latency_runtime}, end to end",
        f"  (median, measured when shipped{load}, over {latency_source}: {latency.candidates:.0f} candidates",
        f"  and {latency.crossings:.0f} crossings found a frame on average"
        + (
            f"; the first stage alone {latency.first_stage_ms:.1f} ms, so the later stages cost "
            f"{latency.second_stage_us_per_candidate:.0f} us a candidate"
            if latency.first_stage_ms is not None
            else ""
        )
        + ").",
        "  `rebar bench --only detector` measures it again beside a YOLOv8n-pose-shaped network. The figures",
        "  above are ONNX Runtime's in float32, the runtime training fits on; `Detector.load` runs OpenVINO in",
        '  bfloat16 where the CPU has it (`runtime="auto"`), which moves them by a few detections.',
        *_reading_lines(detector),
        *_focal_lines(detector),
        f"- Operating threshold: score 0.5, placed at the best F1 on the val split (a logit shift of {detector.score_bias:+.2f}",
        "  stored in the file; it changes no ranking, so AP and recall at a precision do not depend on it)"
        + (
            f";\n  without a depth image the RGB stages' own, placed the same way ({detector.score_bias_without_depth:+.2f})."
            if dc
            else "."
        ),
        "",
        "## Training",
        f"- Data: `{ds.get('name')}` v{ds.get('version')}, its train split (early stopping and the choice of",
        "  epoch on val); the dataset is split by scene, so no frame of a val or test scene was trained on.",
        *_supplement_lines(ds.get("supplements") or []),
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
        f"  scale {tc['augment']['scale']},",
        f"  rotation +-{tc['augment']['rotation_deg']:g} deg and flips (the viewing rays turn with the crop), colour,",
        "  gamma, blur, noise"
        + (
            f"; the hue turned anywhere for {tc['augment']['hue_full_probability']:.0%} of the crops (coatings such as"
            f" epoxy green), white balance +-{tc['augment']['white_balance']:.0%} a channel."
            if tc["augment"].get("hue_full_probability") or tc["augment"].get("white_balance")
            else "."
        ),
        *_distractor_gain_lines(tc["augment"]),
        *_adapt_lines(res, tc, ds),
        *(
            [
                f"- Second stage: {refine['epochs']} epochs over the training split's visible crossings "
                f"({res.get('refine_seconds', 0.0) / 60:.1f} minutes, in the total above),",
                f"  each a {refine['patch_px']} px patch centred with a random error (Gaussian sigma "
                f"{refine['jitter_px']:g} px, or for {refine['jitter_uniform_fraction']:.0%} uniform up to "
                f"{refine['jitter_uniform_px']:g} px),",
                "  turned, flipped, scaled and recoloured like the crops; smooth-L1 loss on the offset. Its positions",
                "  learn from the labels alone, not from the first stage's outputs.",
                *(
                    [
                        f"  {refine['border_fraction']:.0%} of the patches get a border of their own, a straight edge within "
                        f"{refine['border_reach_px']:g} px",
                        "  of the crossing on either side of it, beyond which the patch is blank: so it learns to place",
                        "  a crossing from its part inside the frame.",
                    ]
                    if refine.get("border", "mirror") == "mask"
                    else []
                ),
                *(
                    [
                        f"  Its verification also learns from negatives: the trained first stage's detections (score >= "
                        f"{refine['negative_score']:g})",
                        f"  on the training images farther than {refine['negative_gate_px']:g} px from every "
                        "visible crossing; cross-entropy beside the offset loss.",
                        *(
                            [
                                f"  With them, up to {refine['lower_mat_negatives']} of the crossings each image's lower "
                                "mat shows (its own, and top bars in front of its bars; placed from the tables)."
                            ]
                            if refine.get("lower_mat_negatives")
                            else []
                        ),
                    ]
                    if verifies
                    else []
                ),
                *_refine_supplement_lines(
                    ds.get("refine_supplements") or [],
                    refine,
                    bool(res.get("adapt_epochs")),
                    tc.get("other_renderer_repeats", 0),
                ),
            ]
            if refine
            else []
        ),
        *(
            [
                f"- Depth check: {dc['epochs']} epochs over depth patches around the training images' visible crossings and",
                f"  the second stage's negatives ({res.get('depth_check_seconds', 0.0) / 60:.1f} minutes, in the total above), "
                f"centred with a Gaussian error of {dc['jitter_px']:g} px,",
                f"  turned by quarter turns, flipped, the relative depth scaled by {dc['gain'][0]:g}-{dc['gain'][1]:g}; cross-entropy.",
                *(
                    [
                        f"  Its negatives also hold up to {dc['lower_mat_negatives']} of the crossings each image's lower "
                        "mat shows (its own, and top bars in front of its bars; placed from the tables)."
                    ]
                    if dc.get("lower_mat_negatives")
                    else []
                ),
            ]
            if dc
            else []
        ),
        f"- Occluded crossings (visibility 1): {tc['occluded']} in the loss.",
        "- Reproduce: `make train` (builds the default dataset, its supplements and the planar-slab set when",
        "  missing, trains, and ships this file and card); the settings below are `TrainConfig`'s defaults.",
        "- What was tried for the data and settings, adopted or not, with its figures: the docstrings of",
        "  `TrainConfig` and its stages' settings (`rebar_data/perception/training/config.py`) and the supplements' pipeline files.",
        "",
        "## Metrics",
        f"OKS sigma {sigma:g}; object area = the crossing's square box (side `box_size_px`, four projected bar",
        f"diameters), so OKS 0.5 is reached at {oks_radius_px(sigma, 25):.1f} px for a 25 px box and "
        f"{oks_radius_px(sigma, 40):.1f} px for a 40 px box",
        "(the paper-tunnel median). PCK, errors, precision and recall: Hungarian matching per image with a",
        "5 px gate, predictions of score >= 0.5; recall@P0.99 along the score-sorted predictions. Visible",
        "crossings only (visibility 2). OKS AP is COCOeval's, 101 recall thresholds: each threshold above the",
        "recall reached with every detection counts precision 0. Where more than one crossing in a hundred is",
        "never found within OKS 0.5, AP@0.5 stays under 0.99 however few the false detections (at recall",
        "0.988, at most 0.980); `rebar detect` prints that recall and the ceiling (`metrics.ap_ceiling`).",
        "",
        "| data | crossings | OKS AP@0.5 | AP@0.5:0.95 | PCK@1px | PCK@2px | PCK@5px | mean px | median px | P | R | R@P0.99 |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *rows,
        "",
        f"- `{ds.get('name')} test`: the held-out scenes (other lights, materials, surroundings and camera paths);",
        "  the figure to quote. `val`: the scenes that chose the epoch.",
        f"- `test, crossings >= {BORDER_BAND_PX:g} px inside the frame`: the test split with the crossings within "
        f"{BORDER_BAND_PX:g} px of the",
        "  image border set aside (ignore regions), and the detections there. At the border only part of a",
        "  crossing is in view, and one just outside the frame, which the labels count as no crossing, looks",
        "  much like one just inside it.",
        "- `test, scenes with (without) a lower mat`: the test scenes with a second mat beneath the bars",
        f"  (the samples table's `{LOWER_MAT_COLUMN}`), where a bar passing over the mat beneath looks like a",
        "  crossing; and the others. The rows of another renderer's sets split the same way.",
        "- `random ... of frames`: frames drawn at random from the whole dataset, as the paper's frame-level",
        "  80:20 split draws its test set. Most of them were trained on (and the rest are a few centimetres of",
        "  camera motion from frames that were), so the gap to the test row is what a random split hides.",
        "- `(all splits)` rows: datasets built with other configs (`pipelines/*.yaml`), never trained on.",
        *(
            [
                "- `first stage alone`: the heatmap network's detections without the later stages (its",
                "  positions and scores"
                + (", before verification" if verifies else "")
                + "), to show what they add.",
            ]
            if refine
            else []
        ),
        *(
            [
                "- `without depth`: the same images given to `detect` without their depth images, as a folder of",
                f"  photographs would be: {rgb_path.replace('the RGB', 'the two RGB')}, at their own operating point. The other rows",
                "  (but `first stage alone`) give the detector each image's depth image, as the robot's RGB-D camera does.",
                f"- `{FLATTENED}`: given the depth image, every pixel more than {GAP_M:g} m behind the nearest surface",
                "  around it (the mat beneath, the ground) is first replaced by the blurred colour of such pixels nearby",
                "  (`Detector.flatten_behind`, off by default: it needs the depth image registered to the colour one",
                "  within a pixel; README, the detector section).",
                "- `with depth` rows of another renderer's sets: the same frames given with their depth images; their",
                "  `RGB only` rows leave them out.",
            ]
            if dc
            else []
        ),
        *_census_lines(extra_results or {}),
        "",
        "## Limits",
        _renderer_line(ds),
        *(
            [
                "- One mesh (the paper's tunnel segment, 12 mm bars at 100 mm) and one focal length in training; the",
                "  other-config rows say how far that carries.",
            ]
            if len(ds.get("supplements") or []) <= 1
            else [
                "- The meshes, bars, cameras and looks trained on are those of the pipelines named above; the",
                "  other-config rows (never trained on) and the other renderer's rows say how far they carry.",
            ]
        ),
        *(
            [
                "- The depth check learned from mats with open space behind their bars (the element's far face, the",
                "  mat beneath or the surroundings). Bars lying directly on a surface are outside what it saw: on the",
                "  project's drawn test frames (bars on the ground) it doubts every crossing. Give such images no depth.",
            ]
            if dc
            else []
        ),
        "",
        "## Settings",
        "```json",
        json.dumps(tc, indent=1, sort_keys=True),
        "```",
        "",
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
) -> dict[str, dict]:
    """The card's rows beyond the run's own splits: where the test split's errors lie
    (:func:`~rebar_data.perception.evaluation.evaluate.breakdown`), the training dataset scored as a random frame
    split would test it, and every split of each dataset in ``evaluate_on`` (datasets built with other
    configs).

    Returns:
        Row name -> metrics (as :func:`rebar_data.perception.evaluation.metrics.summary` gives them).
    """
    from rebar_data.perception.evaluation.evaluate import (
        RANDOM_SPLIT_FRACTION,
        breakdown,
        load_splits,
        random_frames,
        score,
        score_dataset,
    )
    from rebar_data.perception.evaluation.false_detections import false_detection_census

    res = json.loads((run_dir / "results.json").read_text())
    rows: dict[str, dict] = {}
    root = Path(res["dataset"].get("path") or "")
    test = load_split(root, "test") if (root / "tables/samples.parquet").exists() else []
    if test:
        preds = predict(detector, test, progress=progress)
        for name, m in breakdown(root, test, preds, sigma=res["oks_sigma"]).items():
            rows[f"{res['dataset'].get('name')} test, {name}"] = m
        if detector.depth_check is not None and any(s.depth_path is not None for s in test):
            # from RGB alone as well, split by scene: where the RGB path's errors lie
            rgb = predict(detector, test, depth=False, progress=progress)
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
            rows[f"{label} (all splits)"] = score_dataset(detector, path, progress=progress)
            continue
        # another renderer's images stand for a user's camera: scored from RGB alone, against the labels
        # and against the projected 3D crossing points (what labels made from the 3D point alone expect)
        sigma = stated_oks_sigma(path)
        samples = load_splits(path)
        preds = predict(detector, samples, depth=False, progress=progress)
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
            rows[f"{label}, {engine} renderer, with depth"] = score(
                samples, predict(detector, samples, progress=progress), sigma=sigma
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
    rows = evaluation_rows(
        detector, run_dir, evaluate_on=evaluate_on, random_split=random_split, progress=progress
    )
    rows.update(extra_results or {})
    from rebar_data.perception.evaluation.gate import GATE_NAME, card_rows, write_reference

    if gate:
        rows.update(card_rows(write_reference(dst, out=models_dir / GATE_NAME)))
    else:
        (models_dir / GATE_NAME).unlink(missing_ok=True)
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
    )
    return dst
