"""Train the crossing detector on a dataset in the project's layout, on the CPU.

A run folder holds everything about one run:

- ``config.json``: the resolved settings, the dataset and its OKS sigma;
- ``last.pt`` (every epoch: weights, weight average, optimiser, random states, history, so an interrupted
  run resumes where it stopped) and ``best.pt`` (the best validation epoch);
- ``adapt_last.pt`` / ``adapted.pt``: the first stage's adapt epochs on another renderer's frames
  (:mod:`~rebar_data.perception.training.adapt`), when the run has second-stage supplements;
- ``best.onnx``: the first stage shipped (``adapted.pt`` when there is one, else ``best.pt``), its score
  bias and results in its metadata; the later stages' files beside it (``best.refine.onnx`` ...);
- ``metrics.csv``: one row per epoch (losses, learning rate, validation metrics, time);
- ``results.json``: the best model's metrics on the validation and test splits;
- ``curves.png``, ``pr_curve.png``, ``predictions.png``.

The epochs done, the run ends with the finishing steps of :mod:`~rebar_data.perception.training.ship`
(export, int8 copy, operating point, line check, scores, results, plots). The weights evaluated and saved are an exponential moving average of the trained ones."""

from __future__ import annotations

import copy
import csv
import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rebar_data.config import ConfigError
from rebar_data.outputs import OutputLock, mark_output, output_folder, replace_file
from rebar_data.perception.evaluation.data import (
    Sample,
    check_dataset,
    load_split,
    read_image,
    read_info,
    renderer_engine,
)
from rebar_data.perception.evaluation.evaluate import first_stage_only, load_splits, predict, score
from rebar_data.perception.evaluation.metrics import DEFAULT_OKS_SIGMA, OPERATING_THRESHOLD, format_summary
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.networks import eager
from rebar_data.perception.networks.files import load_checkpoint, save_checkpoint
from rebar_data.perception.networks.keypoint_net import KeypointNet, count_parameters
from rebar_data.perception.training import crossing_point, depth_check, epochs, refine
from rebar_data.perception.training.adapt import ADAPTED, adapt_first_stage
from rebar_data.perception.training.config import InitConfig, TrainConfig, resolve_config
from rebar_data.perception.training.epochs import training_device
from rebar_data.perception.training.export import STAGES
from rebar_data.perception.training.init import (
    InitModel,
    first_stage_settings,
    parse_stages,
    read_model,
    settings_from,
    stage_settings,
)
from rebar_data.perception.training.run import TrainRun, supplement_names, weights_key
from rebar_data.perception.training.ship import finish
from rebar_data.resume import STEPS_FILE, Steps, key_of

COMMAND = "rebar train"
EARLY_STOP_METRIC = "val_oks_ap"
# settings newer than some run folders, at their old value
NEWER_FIELDS = {"other_renderer_repeats": 0, "init": InitConfig().model_dump(mode="json")}
RESUMABLE_CHANGES = {"epochs", "patience", "val_every", "adapt", "line_check", *STAGES}


@dataclass
class TrainResult:
    """What a run produced: its folder, best and last epoch, whether it stopped early, one row per epoch
    (metrics.csv) and the best model's metrics per split."""

    out_dir: Path
    best_epoch: int
    epochs_run: int
    stopped_early: bool
    history: list[dict[str, Any]] = field(default_factory=list)
    results: dict[str, dict[str, float]] = field(default_factory=dict)


def is_run_folder(folder: Path) -> bool:
    """``folder`` has a run folder's layout (runs from before the mark): config.json and a checkpoint."""
    return (folder / "config.json").is_file() and any((folder / n).is_file() for n in ("last.pt", "best.pt"))


def check_run_folder(out: str | Path) -> Path:
    """``out`` as a run may be written there: new, empty, or an earlier run; anything else is refused."""
    return output_folder(out, arg="--out", command=COMMAND, owned=is_run_folder)


def train(
    dataset_path: str | Path,
    out_dir: str | Path,
    *,
    config: TrainConfig | dict | None = None,
    epochs: int | None = None,
    batch_size: int | None = None,
    supplements: Sequence[str | Path] = (),
    refine_supplements: Sequence[str | Path] = (),
    line_supplements: Sequence[str | Path] = (),
    resume: bool = True,
    progress: bool = True,
    init: str | Path | InitModel | None = None,
    stages: str | Sequence[str] | None = None,
    device: str = "auto",
) -> TrainResult:
    """Train (or resume training) a detector and write the run folder.

    Args:
        dataset_path: A dataset folder (``ROOT/<name>/v<version>/``) with train, val and test splits.
        out_dir: The run folder: new, empty or an earlier run (which resumes when ``resume``).
        config: Settings; defaults are what ``make train`` uses.
        epochs: Overrides ``config.epochs``.
        batch_size: Overrides ``config.batch_size``.
        supplements: Datasets whose every image joins the training images (val and test stay the first's).
        refine_supplements: Datasets (another renderer's frames) whose every image trains the adapt epochs
            and the second stage, and the first epochs with ``config.other_renderer_repeats``.
        line_supplements: Datasets whose every image the line check is fitted on beside the val split.
        resume: Continue from ``out_dir/last.pt`` if it exists (with the same settings but for
            ``RESUMABLE_CHANGES``); False starts afresh.
        progress: Show a progress bar per epoch and a summary line after it (on stderr).
        init: A model to start from (:mod:`~rebar_data.perception.training.init`): its ``.onnx`` file or an
            :class:`~.init.InitModel`; its settings are the run's, ``config`` (a dict) laid over them.
        stages: With ``init``, the stages to train (names in :data:`~.init.STAGE_NAMES`, or a comma-separated
            list); the others are kept as the model has them. None: every stage.
        device: Where the networks train (:func:`~.epochs.training_device`: ``auto`` is the GPU where there
            is one); detection, scoring and export stay on the CPU, as the run time reads the model."""
    if init is None and stages is not None:
        raise ConfigError(
            "--stages picks what to train from a model; accepted: --stages together with --init"
        )
    chosen = parse_stages(stages)
    model = init if isinstance(init, InitModel) or init is None else read_model(init)
    if model is not None and not isinstance(config, TrainConfig):
        config = settings_from(model, config, source="train settings")
    cfg = resolve_config(config, {"epochs": epochs, "batch_size": batch_size})
    root = check_dataset(dataset_path)
    out = check_run_folder(out_dir)
    info = read_info(root)
    sigma = float(info.get("oks_sigma", DEFAULT_OKS_SIGMA))
    samples = load_split(root, "train")
    if not samples:
        raise ConfigError(f"{root}: the train split has no images; accepted: a dataset with training images")
    extra, extra_meta = supplement_images(supplements, trained_on=info.get("name"))
    samples = samples + extra
    refine_extra, refine_meta = supplement_images(refine_supplements, trained_on=info.get("name"))
    line_extra, line_meta = supplement_images(line_supplements, trained_on=info.get("name"))
    if cfg.depth_check.enabled:  # fail now, not after the first two stages have trained
        depth_check.check_depth(samples)
    dataset = {**_record(root, info), "supplements": extra_meta, "refine_supplements": refine_meta}
    val, test = load_split(root, "val"), load_split(root, "test")
    if model is not None:
        dataset["init"] = model.record(chosen)
    run = TrainRun(
        cfg, out, sigma, dataset, samples, val, test, refine_extra, line_extra, line_meta, progress
    )
    run.init, run.stages, run.device = model, chosen, training_device(device)
    run.steps = Steps(out / STEPS_FILE, log=run.log)
    threads_before = torch.get_num_threads()
    with OutputLock(out, command=COMMAND):
        check_run_folder(out)  # again under the lock: another run may have written there meanwhile
        out.mkdir(parents=True, exist_ok=True)
        mark_output(out, COMMAND)
        torch.set_num_threads(cfg.threads)
        try:
            state = _first_stage(run, resume)
            # the first stage to ship: the best epoch, then its adapt epochs on the second-stage supplements
            first_path, adapt_history = adapt_first_stage(
                out,
                cfg,
                run.train,
                refine_extra if run.trains("first") else [],
                base_epoch=state["best_epoch"],
                data=supplement_names(refine_meta),
                log=run.log,
                progress=progress,
                device=run.device,
            )
            stages = _later_stages(run, state, first_path)
            results = finish(run, state, first_path, {"adapt": (None, adapt_history), **stages})
            return TrainResult(
                out, state["best_epoch"], state["epoch"], state["stopped"], state["history"], results
            )
        finally:
            torch.set_num_threads(threads_before)


def supplement_images(
    supplements: Sequence[str | Path], *, trained_on: str | None
) -> tuple[list[Sample], list[dict[str, Any]]]:
    """Every image of each supplement, and what the run records of each (:func:`_record` and its images)."""
    images: list[Sample] = []
    meta: list[dict[str, Any]] = []
    for path in supplements:
        root = check_dataset(path)
        info = read_info(root)
        if info.get("name") == trained_on:
            raise ConfigError(
                f"{root}: is a build of {trained_on!r}, the dataset trained on, whose val and test scenes a "
                "supplement would train on; accepted: a dataset built from another pipeline"
            )
        these = load_splits(root)
        if not these:
            raise ConfigError(f"{root}: the supplement has no images; accepted: a dataset with images")
        images += these
        meta.append({**_record(root, info), "images": len(these)})
    return images, meta


def _record(root: Path, info: dict[str, Any]) -> dict[str, Any]:
    """What a run records of a dataset: its path, name, version and renderer."""
    return dict(
        path=str(root), name=info.get("name"), version=info.get("version"), renderer=renderer_engine(info)
    )


def _check_resumable(saved: dict[str, Any], cfg: TrainConfig, path: Path) -> None:
    """ConfigError unless the run ``saved`` settings describe may resume with ``cfg``."""
    now = cfg.model_dump(mode="json")
    for k in sorted(set(saved) | set(now)):
        was = saved.get(k, NEWER_FIELDS.get(k))
        if k not in RESUMABLE_CHANGES and was != now.get(k):
            raise ConfigError(
                f"{path}: holds a run with {k} = {was!r}, not {now.get(k)!r}; accepted: the same "
                "settings to resume, or a fresh start (--fresh) or another run folder"
            )


def _check_same_supplements(payload: dict[str, Any], run: TrainRun, path: Path) -> None:
    """ConfigError unless the run in ``payload`` trained its first epochs on ``run``'s supplements."""
    # the second-stage supplements count when they trained the first epochs too
    for key in ("supplements", "refine_supplements")[: 1 + bool(run.cfg.other_renderer_repeats)]:
        was, now_names = (
            supplement_names(payload["meta"]["dataset"].get(key, [])),
            supplement_names(run.dataset[key]),
        )
        if was != now_names:
            raise ConfigError(
                f"{path}: holds a run trained with supplements {was or 'none'}, not {now_names or 'none'}; "
                "accepted: the same supplements to resume, or a fresh start (--fresh) or another run folder"
            )


def _kept_first_stage(run: TrainRun) -> dict[str, Any]:
    """The init model's first stage as the run's ``best.pt``, untrained; returns the state."""
    init = run.init
    meta = {**init.meta, "dataset": run.dataset, "train_config": run.cfg.model_dump(mode="json")}
    save_checkpoint(run.out / "best.pt", init.first, meta)
    (run.out / "last.pt").unlink(
        missing_ok=True
    )  # epochs of an earlier run in this folder are not this one's
    config = {"train_config": run.cfg.model_dump(mode="json"), "dataset": run.dataset, "oks_sigma": run.sigma}
    config["parameters"] = count_parameters(init.first)
    (run.out / "config.json").write_text(json.dumps(config, indent=2, sort_keys=True) + "\n")
    run.log(f"first stage kept: {init.source}")
    return dict(
        epoch=0, step=0, best=-1.0, best_epoch=int(init.meta.get("epoch", 0)), stopped=True, history=[]
    )


def _first_stage(run: TrainRun, resume: bool) -> dict[str, Any]:
    """Train the first stage's epochs (resuming ``last.pt``), the best in ``best.pt``; returns the state. From
    an init model: its first stage trains on (:func:`~.init.first_stage_settings`), or is kept as it is."""
    if run.kept("first"):
        return _kept_first_stage(run)
    cfg, out = run.cfg, run.out
    frozen = run.init is not None
    if frozen:
        cfg = first_stage_settings(cfg)
    torch.manual_seed(cfg.seed)
    # channels-last: the depthwise convolutions train faster on a CPU in that layout
    net = copy.deepcopy(run.init.first) if frozen else KeypointNet(cfg.model)
    net = net.to(run.device, memory_format=torch.channels_last)
    avg = epochs.WeightAverage(net)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    state: dict[str, Any] = dict(epoch=0, step=0, best=-1.0, best_epoch=0, stopped=False, history=[])
    last = out / "last.pt"
    if resume and last.exists():
        _, _, payload = load_checkpoint(last)
        if payload.get("init") != run.init_record:
            raise ConfigError(
                f"{last}: holds a run that started from {_start(payload.get('init'))}, not "
                f"{_start(run.init_record)}; accepted: the same start to resume, or a fresh start "
                "(--fresh) or another run folder"
            )
        _check_resumable(payload["train_config"], cfg, last)
        _check_same_supplements(payload, run, last)
        state = epochs.restore(payload, net, avg, opt)
        run.log(f"resuming {out} after epoch {state['epoch']}")
    config = {
        "train_config": cfg.model_dump(mode="json"),
        "dataset": run.dataset,
        "oks_sigma": run.sigma,
        "parameters": count_parameters(net),
    }
    (out / "config.json").write_text(json.dumps(config, indent=2, sort_keys=True) + "\n")
    # an even spread of at most val_max_images (all of them when there are no more)
    spread = np.linspace(0, len(run.val) - 1, min(len(run.val), cfg.val_max_images)).round().astype(int)
    val_sub = [run.val[i] for i in spread]
    val_images = [read_image(s.path) for s in val_sub] if cfg.cache_images else None
    base_meta = {
        "dataset": run.dataset,
        "oks_sigma": run.sigma,
        "threshold": OPERATING_THRESHOLD,
        "focal_per_width": float(np.median([s.camera[0] / s.width for s in run.train])),
        # the focal length the first stage learns at: `Detector.detect` reads other cameras' frames at it
        "focal_px": float(np.median([0.5 * (s.camera[0] + s.camera[1]) for s in run.train])),
        **(
            {k: run.init.meta[k] for k in ("focal_per_width", "focal_px") if k in run.init.meta}
            if frozen
            else {}
        ),
        "train_config": cfg.model_dump(mode="json"),
    }
    # the first epochs' images: the training images, then the second-stage supplements' repeated
    first_samples = run.train + run.refine_extra * cfg.other_renderer_repeats
    steps = max(1, math.ceil(len(first_samples) * cfg.crops_per_image / cfg.batch_size))
    run.started = time.perf_counter()
    if not state["stopped"] and state["epoch"] < cfg.epochs:
        first, focal_px = state["epoch"] + 1, base_meta["focal_px"]
        batches = epochs.batch_stream(
            first_samples, cfg, first=first, last=cfg.epochs, steps=steps, focal_px=focal_px
        )
    for epoch in range(state["epoch"] + 1, cfg.epochs + 1):
        if state["stopped"]:
            break
        row = epochs.train_epoch(
            net,
            avg,
            opt,
            batches,
            cfg,
            state,
            epoch=epoch,
            steps=steps,
            progress=run.progress,
            frozen_norm=frozen,
            device=run.device,
        )
        line = f"epoch {epoch}/{cfg.epochs}: loss {row['train_loss']:.4f}"
        if val_sub and (epoch % cfg.val_every == 0 or epoch == cfg.epochs):
            on_cpu = copy.deepcopy(avg.net).cpu()  # the run time's numpy path reads CPU tensors
            m = score(val_sub, predict(eager.detector(on_cpu), val_sub, images=val_images), sigma=run.sigma)
            row.update({f"val_{k}": v for k, v in m.items() if k not in ("oks_sigma", "threshold")})
            line += f"; val {format_summary(m)}"
        run.log(line)
        state["history"].append(row)
        state["epoch"] = epoch
        meta = {**base_meta, "epoch": epoch}
        key = row.get(EARLY_STOP_METRIC)
        if key is None and not val_sub:
            key = -row["train_loss"]  # no validation split: keep the latest weights
        if key is not None and np.isfinite(key) and key > state["best"]:
            state["best"], state["best_epoch"] = float(key), epoch
            save_checkpoint(out / "best.pt", avg.net, meta)
        elif key is not None and epoch - state["best_epoch"] >= cfg.patience:
            state["stopped"] = True
            run.log(f"early stop: no better {EARLY_STOP_METRIC} for {cfg.patience} epochs")
        resumable = epochs.checkpoint_state(net, avg, opt, state)
        train_config = cfg.model_dump(mode="json")
        save_checkpoint(last, net, meta, train_config=train_config, init=run.init_record, **resumable)
        _write_history(out / "metrics.csv", state["history"])
    batches = None  # stops the loader process
    if not (out / "best.pt").exists():  # no epoch had a finite validation score: keep the latest weights
        save_checkpoint(out / "best.pt", avg.net, {**base_meta, "epoch": state["epoch"]})
    return state


def _start(record: dict[str, Any] | None) -> str:
    """A run's start as an error names it: nothing, or the model and the stages trained from it."""
    if not record:
        return "nothing (no --init)"
    return f"{record['model']} (sha256 {record['sha256'][:16]}, stages {','.join(record['stages'])})"


def _later_stages(run: TrainRun, state: dict[str, Any], first_path: Path) -> dict[str, tuple[Any, list]]:
    """Train the later stages the settings enable; returns each one's network (None when off) and history."""
    cfg, out = run.cfg, run.out
    # what the later stages' negatives come from: a changed first stage trains them again
    negatives_from = [f"first stage: epoch {state['best_epoch']}"]
    if run.init is not None:
        negatives_from = [
            f"first stage: {run.init.source}"
            + (f", epoch {state['best_epoch']}" if run.trains("first") else "")
        ]
    if first_path.name == ADAPTED:
        negatives_from.append(f"adapted: {json.dumps(cfg.adapt.model_dump(mode='json'), sort_keys=True)}")
    found: dict[int, list[np.ndarray]] = {}  # the first stage's detections, run once a sample list

    def negatives_of(samples: list[Sample], images: list[np.ndarray]) -> list[np.ndarray]:
        if id(samples) not in found:
            first, _, _ = load_checkpoint(first_path)
            # a step: the first stage's detections on these images, kept in steps.json for a later run
            key = key_of(weights_key(first), [str(s.path) for s in samples], cfg.refine.negative_score)

            def mine() -> list:
                if run.kept("first"):  # the model's own file (faster), read as the network below reads:
                    detector = Detector.load(
                        run.init.path, threads=2, runtime="onnxruntime", reading="single"
                    )
                    detector.score_bias, detector.focal_px = 0.0, None  # no operating point, no resampling
                else:
                    detector = eager.detector(first)
                with first_stage_only(detector):
                    ran = refine.first_stage_detections(
                        detector, samples, cfg.refine, images=images, progress=run.progress
                    )
                return [p.tolist() for p in ran]

            mined = run.steps.run("first-stage detections", key, mine)
            found[id(samples)] = [np.asarray(p, float).reshape(-1, 3) for p in mined]
        return refine.negatives_in(found[id(samples)], samples, cfg.refine)  # the first stage's misses

    def depth_negatives() -> list[np.ndarray]:
        """The second stage's mined negatives (its checkpoint's, else mined now) and the lower mat's."""
        mined = None
        if (out / "refine_last.pt").exists():
            mined = refine.load(out / "refine_last.pt")[2].get("negatives")
        if mined is None or len(mined) != len(refine_samples) or not any(len(n) for n in mined):
            mined = negatives_of(run.train, [read_image(s.path) for s in run.train])
        mined = mined[: len(run.train)]  # the second stage's images begin with the first's
        n = cfg.depth_check.lower_mat_negatives
        return refine.with_lower_mat(
            run.train, mined, n, gate_px=cfg.refine.negative_gate_px, seed=cfg.seed + 1
        )

    # the second stage's images: the first's, then each second-stage supplement's, repeated
    refine_samples = run.train + run.refine_extra * cfg.refine.supplement_repeats
    stages: dict[str, tuple[Any, list]] = {k: (None, []) for k in ("refine", "depth_check", "crossing_point")}
    for key in stages:
        if not getattr(cfg, key).enabled:
            continue
        if run.kept(key):
            stages[key] = (run.init.stages[key], [])
            run.log(f"{key} kept: {run.init.source}")
            continue
        if run.init is not None and not run.trains(key):
            continue  # not named, and the init model has none to keep
        start = run.init.stages.get(key) if run.init is not None else None
        settings = getattr(cfg, key) if start is None else stage_settings(cfg, key)
        since = [] if start is None else [f"from {run.init.source}"]
        if key == "refine":
            stages[key] = refine.train_refiner(
                refine_samples,
                out,
                settings,
                cfg.augment,
                seed=cfg.seed,
                negatives_of=negatives_of,
                data=supplement_names(run.dataset["refine_supplements"]) + negatives_from + since,
                progress=run.progress,
                init=start,
                device=run.device,
            )
        elif key == "depth_check":
            n = settings.lower_mat_negatives
            stages[key] = depth_check.train_depth_check(
                run.train,
                depth_negatives,
                out,
                settings,
                seed=cfg.seed,
                data=negatives_from
                + ([f"its own lower-mat negatives: {n}"] if n else [])
                + ["sensor depth"]
                + since,
                progress=run.progress,
                init=start,
                device=run.device,
            )
        else:
            stages[key] = crossing_point.train_crossing_point(
                run.train,
                out,
                settings,
                cfg.augment,
                seed=cfg.seed,
                progress=run.progress,
                init=start,
                data=since,
                device=run.device,
            )
    run.train_seconds = time.perf_counter() - run.started
    return stages


def _write_history(path: Path, history: list[dict[str, Any]]) -> None:
    keys = list(dict.fromkeys(k for row in history for k in row))

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=keys)
            w.writeheader()
            w.writerows(
                {k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()} for row in history
            )

    replace_file(path, write)
