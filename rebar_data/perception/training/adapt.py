"""The first stage's adapt epochs: after its best epoch, a few more at a low learning rate on its training
images and another renderer's frames (the second-stage supplements, repeated), batch norms frozen. They
train the first stage the run ships, again whenever their settings, data or that best epoch change.

In the run folder: ``adapt_last.pt`` (after every epoch, to resume) and ``adapted.pt`` (the weight average
after the last epoch, in ``best.pt``'s format)."""

from __future__ import annotations

import math
from contextlib import suppress
from pathlib import Path
from typing import Any

import torch

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import Sample
from rebar_data.perception.networks import files
from rebar_data.perception.training.config import TrainConfig, resolve_config
from rebar_data.perception.training.epochs import (
    WeightAverage,
    batch_stream,
    checkpoint_state,
    restore,
    train_epoch,
)

ADAPT_LAST = "adapt_last.pt"
ADAPTED = "adapted.pt"
ADAPT_FORMAT = "rebar-adapt"
# the adapt epochs' batches come from generators of their own (seed + this, epoch), not the first epochs'
SEED_OFFSET = 7919


def adapt_first_stage(
    out: Path,
    cfg: TrainConfig,
    samples: list[Sample],
    extra: list[Sample],
    *,
    base_epoch: int,
    data: list[str],
    log=None,
    progress: bool = False,
    device: torch.device | str = "cpu",
) -> tuple[Path, list[dict[str, Any]]]:
    """Train the adapt epochs from ``out/best.pt`` (epoch ``base_epoch``) on ``samples`` and ``extra``
    (repeated), or take them from the run folder when they trained on the same settings, ``data`` and best
    epoch. Returns the first stage to ship (``best.pt`` without adapt epochs or ``extra``) and the history."""
    a = cfg.adapt
    if a.epochs == 0 or not extra:
        for stale in (out / ADAPT_LAST, out / ADAPTED):
            stale.unlink(missing_ok=True)
        return out / "best.pt", []
    want = {"adapt": a.model_dump(mode="json"), "base_epoch": base_epoch, "data": list(data)}
    net, meta, _ = files.load_checkpoint(out / "best.pt")
    net = net.to(device, memory_format=torch.channels_last)
    avg = WeightAverage(net)
    opt = torch.optim.AdamW(net.parameters(), lr=a.lr, weight_decay=cfg.weight_decay)
    state: dict[str, Any] = {"epoch": 0, "step": 0, "history": []}
    path = out / ADAPT_LAST
    saved = None
    if path.exists():
        with suppress(ConfigError):  # unreadable: trained afresh
            saved = files.read_checkpoint(path, fmt=ADAPT_FORMAT, what="adapt")
    if saved is not None and saved["want"] == want:
        state = restore(saved, net, avg, opt)
        if state["epoch"] >= a.epochs and (out / ADAPTED).exists():
            return out / ADAPTED, state["history"]
    (out / ADAPTED).unlink(missing_ok=True)
    mix = samples + extra * a.supplement_repeats
    # the first epochs' machinery: a cosine decay from a.lr over the adapt epochs, no mosaic, own batches
    update = dict(epochs=a.epochs, lr=a.lr, warmup_epochs=a.warmup_epochs, seed=cfg.seed + SEED_OFFSET)
    run = cfg.model_copy(update={**update, "augment": cfg.augment.model_copy(update={"mosaic_epochs": 0})})
    steps = max(1, math.ceil(len(mix) * cfg.crops_per_image / cfg.batch_size))
    if log:
        log(
            f"adapt epochs: {a.epochs} from the first stage's epoch {base_epoch}, {len(samples)} images and "
            f"{len(extra)} x {a.supplement_repeats} of {', '.join(data)}"
        )
    first, focal_px = state["epoch"] + 1, meta.get("focal_px")  # other cameras' frames drawn at the model's
    batches = batch_stream(mix, run, first=first, last=a.epochs, steps=steps, focal_px=focal_px)
    for epoch in range(state["epoch"] + 1, a.epochs + 1):
        row = train_epoch(
            net,
            avg,
            opt,
            batches,
            run,
            state,
            epoch=epoch,
            steps=steps,
            progress=progress,
            frozen_norm=True,
            device=device,
        )
        if log:
            log(f"adapt epoch {epoch}/{a.epochs}: loss {row['train_loss']:.4f}")
        state["history"].append({**row, "seconds": row["train_seconds"]})
        state["epoch"] = epoch
        payload = {"format": ADAPT_FORMAT, "want": want, "state_dict": net.state_dict()}
        files.write_checkpoint(path, {**payload, **checkpoint_state(net, avg, opt, state)})
    batches = None  # stops the loader process
    files.save_checkpoint(out / ADAPTED, avg.net, {**meta, "adapt": {**want, "epochs_run": state["epoch"]}})
    return out / ADAPTED, state["history"]


def adapt_model(
    model: Path,
    samples: list[Sample],
    extra: list[Sample],
    out: Path,
    cfg: TrainConfig | None = None,
    *,
    data: list[str],
    log=None,
    progress: bool = False,
) -> Path:
    """The adapt epochs from a model file: ``model``'s first stage trains ``cfg.adapt``'s epochs (``cfg``
    None: the model's own settings) on ``samples`` and ``extra`` in ``out`` (resumable), and is written to
    ``out/rebar_keypoint.onnx`` beside a copy of the model's later stages."""
    import shutil

    from rebar_data.perception.inference.model_file import stage_files

    if model.suffix != ".onnx":
        raise ConfigError(
            f"{model}: is not an ONNX file; accepted: a model's .onnx file (the shipped one by default)"
        )
    if not extra:
        raise ConfigError(
            "no frames to adapt to; accepted: one or more datasets of the other camera's frames"
        )
    net, meta = files.network_from_onnx(model)
    if cfg is None:
        cfg = resolve_config(meta.get("train_config"), {}, source=f"{model}'s train settings")
    if cfg.adapt.epochs == 0:
        raise ConfigError("adapt.epochs = 0 trains nothing; accepted: 1 or more adapt epochs")
    out.mkdir(parents=True, exist_ok=True)
    files.save_checkpoint(out / "best.pt", net, meta)
    first, _ = adapt_first_stage(
        out, cfg, samples, extra, base_epoch=int(meta.get("epoch", 0)), data=data, log=log, progress=progress
    )
    adapted, adapted_meta, _ = files.load_checkpoint(first)
    target = out / "rebar_keypoint.onnx"
    for a, b in zip(stage_files(model), stage_files(target), strict=True):
        if a.exists():
            shutil.copy2(a, b)
    # the first stage last: a file there means the whole model is there
    return files.export_onnx(
        adapted, target, {**meta, "adapt": adapted_meta.get("adapt", {}), "adapted_from": str(model)}
    )
