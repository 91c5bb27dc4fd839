"""The shipping steps ``export`` and ``int8 copy`` (:mod:`.ship`): a run's first stage and later stages
written as the model files the run time reads, in the run folder (``best.onnx``, ``best.refine.onnx`` ...),
each with its ``.pt`` file and its entry in the first stage's metadata."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rebar_data.digest import sha256_file
from rebar_data.outputs import replace_file
from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.networks.files import export_onnx, load_checkpoint, quantize_onnx
from rebar_data.perception.networks.keypoint_net import KeypointNet
from rebar_data.perception.training import crossing_point, depth_check, refine
from rebar_data.perception.training.run import TrainRun, supplement_names, weights_key
from rebar_data.resume import key_of

# the later stages' files: best.<name>.pt
STAGES = {"refine": "refine", "depth_check": "depth", "crossing_point": "crossing"}
STAGE_META = ("refiner", "depth_check", "crossing_point", "line_check")  # the later stages' metadata entries
DEPTH_CHECK_META = {"patch_px", "scale_m", "clip", "veto_power", "veto_margin"}  # its entry's settings


@dataclass
class Exported:
    """A run's model as the export step wrote it: the first stage's checkpoint (best or adapted) and network,
    its metadata (to which the later steps add the operating point, the line check and the results), the
    detector its files load into and the key of what the steps after it read."""

    first_path: Path
    net: KeypointNet
    meta: dict[str, Any]
    detector: Detector
    model_key: str


def export_model(run: TrainRun, first_path: Path, stages: dict[str, tuple[Any, list]]) -> Exported:
    """Export ``first_path`` (best or adapted) and the later ``stages`` (key -> network, None when off, and
    history) to ONNX in the run folder, and load them as the run time does, in float32."""
    cfg, out = run.cfg, run.out
    net, meta, _ = load_checkpoint(first_path)
    stale = ("score_bias", "results", *STAGE_META)
    meta = {k: v for k, v in meta.items() if k not in stale}
    # the run as it finished (its later stages may have trained on other settings or data)
    meta.update(dataset=run.dataset, train_config=cfg.model_dump(mode="json"))
    files = export_stages(run, stages, meta)
    detector = Detector.load(
        export_onnx(net, out / "best.onnx", meta), threads=cfg.threads, runtime="onnxruntime"
    )
    # what the steps below read: the first stage's weights and every later stage's file
    stage_keys = {k: sha256_file(f) for k, f in files.items()}
    int8 = model_file.int8_passes_path(out / "best.onnx")
    if int8.exists():
        stage_keys["int8"] = sha256_file(int8)
    model_key = key_of(weights_key(net), stage_keys, meta.get("refiner"), meta.get("depth_check"))
    return Exported(first_path, net, meta, detector, model_key)


def export_stages(
    run: TrainRun, stages: dict[str, tuple[Any, list]], meta: dict[str, Any]
) -> dict[str, Path]:
    """Write each later stage's ``.pt`` and ONNX file (a kept stage's file copied from the init model) and its
    meta entry; returns the ONNX files by stage."""
    cfg, out = run.cfg, run.out
    for name in STAGES.values():
        for suffix in ("onnx", "pt"):
            (out / f"best.{name}.{suffix}").unlink(missing_ok=True)
    int8 = model_file.int8_passes_path(out / "best.onnx")
    files: dict[str, Path] = {}
    for module, (key, name) in zip((refine, depth_check, crossing_point), STAGES.items(), strict=True):
        net = stages[key][0]
        if net is None:
            continue
        target = out / f"best.{name}.onnx"
        if run.kept(key):  # byte for byte, so its SHA-256 and int8 copy stay the model's
            replace_file(target, lambda tmp, src=run.init.files[key]: shutil.copyfile(src, tmp))
            module.save(out / f"best.{name}.pt", net, getattr(run.init.trained_with, key))
            files[key] = target
        else:
            module.save(out / f"best.{name}.pt", net, getattr(cfg, key))
            files[key] = export_onnx(net, target)
    if run.kept("refine") and "refine" in files:
        meta["refiner"] = dict(run.init.meta["refiner"])
        if "int8" in run.init.files:
            replace_file(int8, lambda tmp: shutil.copyfile(run.init.files["int8"], tmp))
        else:
            int8.unlink(missing_ok=True)
    elif "refine" in files:
        r = cfg.refine
        kept = {"patch_px", "iterations", "step", "quantize", "verify_power", "views", "first_pass_views"}
        meta["refiner"] = r.model_dump(include=kept) | {
            "shrink_above_px": list(r.shrink_above_px) if r.size else None,
            "verify": stages["refine"][0].verify,
            "sha256": sha256_file(files["refine"]),
        }
        if r.quantize == "later":  # an int8 copy beside it for the passes after the first
            meta["refiner"] |= int8_copy(run, files["refine"], int8)
        else:
            int8.unlink(missing_ok=True)
    else:
        int8.unlink(missing_ok=True)
    for key, kept in (("depth_check", DEPTH_CHECK_META), ("crossing_point", {"patch_px"})):
        if key in files:
            own = getattr(run.init.trained_with if run.kept(key) else cfg, key)
            entry = run.init.meta.get(key) if run.kept(key) else None
            meta[key] = entry or own.model_dump(include=kept) | {"sha256": sha256_file(files[key])}
    return files


def int8_copy(run: TrainRun, refine_file: Path, int8: Path) -> dict[str, Any]:
    """The second stage's int8 copy for its later passes (a step: reused while its float file and settings
    are the same); returns its meta entry's part."""
    r, steps = run.cfg.refine, run.steps
    key = key_of(
        sha256_file(refine_file),
        r.model_dump(mode="json"),
        run.cfg.seed,
        supplement_names(run.dataset["supplements"]),
    )
    if (
        steps.done("int8 copy", key)
        and int8.exists()
        and sha256_file(int8) == steps.result("int8 copy")["int8_sha256"]
    ):
        run.log("int8 copy: done before, reused")
        return steps.result("int8 copy")
    run.log("int8 copy ...")
    patches = refine.calibration_patches(run.train, r, seed=run.cfg.seed)
    quantize_onnx(refine_file, int8, patches)
    run.log(f"second stage's later passes quantized to int8 ({len(patches)} calibration patches)")
    calibrated_on = [f"{run.dataset.get('name')} train"] + supplement_names(run.dataset["supplements"])
    entry = {
        "int8_sha256": sha256_file(int8),
        "int8_calibrated_on": {"data": calibrated_on, "patches": len(patches)},
    }
    steps.keep("int8 copy", key, entry)
    return entry
