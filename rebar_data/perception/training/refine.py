"""Training and model files of the detector's second stage (:mod:`rebar_data.perception.inference.refine`).

The refiner trains on its own, from the labels alone: patches around the training split's visible
crossings, centred with a random error like the first stage's (a Gaussian and, for some, a uniform error
up to ``jitter_uniform_px``), turned, flipped and scaled with the keypoint by the same similarity maps as
the first stage's crops (:func:`~rebar_data.perception.training.augment.random_affine`), with the same colour, blur
and noise changes. So the two stages' positions train independently, and the refiner never learns one
first-stage network's quirks. Its verification output (``RefineConfig.verify``) is the one part that
looks at the first stage: its negatives are where the trained first stage finds crossings that are not
there (:func:`mine_negatives`).
"""

from __future__ import annotations

import copy
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import Sample, read_image, read_images
from rebar_data.perception.evaluation.lower_mat import lower_mat_of
from rebar_data.perception.networks.files import read_checkpoint
from rebar_data.perception.networks.stages import PatchNet
from rebar_data.perception.training.checkpoints import (
    calibration_points,
    fit_weights,
    resume_stage,
    save_stage,
)
from rebar_data.perception.training.config import AugmentConfig, RefineConfig
from rebar_data.perception.training.refine_data import patch_batches, steps_per_epoch
from rebar_data.perception.training.schedule import warmup_cosine

FORMAT = "rebar-keypoint-refiner"
FORMAT_VERSION = 1
# RefineConfig settings that leave training alone: they shape the exported file or how its output is used
EXPORT_ONLY = {
    "quantize",
    "calibration_patches",
    "verify_power",
    "verify_power_with_depth",
    "views",
    "first_pass_views",
    "iterations",
    "step",
    "shrink_above_px",
}


def build(cfg: RefineConfig) -> PatchNet:
    """The refiner network these settings describe."""
    return PatchNet(
        cfg.patch_px,
        cfg.widths,
        cfg.hidden,
        cfg.blocks,
        verify=cfg.verify,
        size=cfg.size,
    )


def save(path: Path, net: PatchNet, cfg: RefineConfig, **extra: Any) -> None:
    save_stage(
        path, fmt=FORMAT, version=FORMAT_VERSION, config_key="refine_config", cfg=cfg, net=net, **extra
    )


def load(path: str | Path) -> tuple[PatchNet, RefineConfig, dict[str, Any]]:
    """Rebuild a refiner from its ``.pt`` file: (network in eval mode, its settings, the whole payload)."""
    payload = read_checkpoint(path, fmt=FORMAT, what="refiner")
    settings = dict(payload["refine_config"])
    settings.setdefault("verify", False)  # written before the second stage could verify
    settings.setdefault("size", False)  # written before it could size a crossing
    cfg = RefineConfig.model_validate(settings)
    net = fit_weights(build(cfg), payload, path, retrain=" (train the second stage again)")
    return net, cfg, payload


def calibration_patches(
    samples: list[Sample], cfg: RefineConfig, *, seed: int, images_used: int = 64
) -> np.ndarray:
    """Patches as the refiner meets them at inference, to set the int8 file's value ranges: cut on the
    pixel grid (:func:`~rebar_data.perception.inference.refine.patches`) around
    :func:`~rebar_data.perception.training.checkpoints.calibration_points`.

    Returns:
        (``cfg.calibration_patches``, P, P, C) uint8 patches (fewer when the images hold fewer crossings).
    """
    from rebar_data.perception.inference.refine import patches

    rng = np.random.default_rng(np.random.SeedSequence([seed, 4099]))
    points = calibration_points(
        samples, count=cfg.calibration_patches, jitter_px=cfg.jitter_px, rng=rng, images_used=images_used
    )
    cut = [patches(read_image(s.path), uv, cfg.patch_px, border="mask") for s, uv in points]
    out = [x for x, _ in cut]
    if not out:
        raise ConfigError(
            "no visible crossings to calibrate the int8 second stage on; accepted: quantize: none"
        )
    return np.concatenate(out)[: cfg.calibration_patches]


def learning_rate(step: int, total: int, cfg: RefineConfig) -> float:
    """Linear warm-up over the first 3% of steps, then cosine decay to 2% of the peak."""
    return warmup_cosine(step, peak=cfg.lr, warm=max(1, round(0.03 * total)), total=total)


def mine_negatives(
    detector, samples: list[Sample], cfg: RefineConfig, *, images: list[np.ndarray], progress: bool = False
) -> list[np.ndarray]:
    """Where ``detector`` (the trained first stage alone) finds crossings that are not there: per sample,
    its detections scoring at least ``cfg.negative_score`` that lie farther than ``cfg.negative_gate_px``
    from every visible crossing, as (M, 2) u, v."""
    return negatives_in(
        first_stage_detections(detector, samples, cfg, images=images, progress=progress), samples, cfg
    )


def negatives_in(found: list[np.ndarray], samples: list[Sample], cfg: RefineConfig) -> list[np.ndarray]:
    """:func:`mine_negatives` from each sample's first-stage detections ``found``
    (:func:`first_stage_detections`)."""
    out = []
    for s, p in zip(samples, found, strict=True):
        uv = p[:, :2].reshape(-1, 2)
        if len(s.visible) and len(uv):
            gap = np.linalg.norm(uv[:, None, :] - s.visible[None, :, :], axis=2).min(axis=1)
            uv = uv[gap > cfg.negative_gate_px]
        out.append(np.ascontiguousarray(uv, np.float64))
    return out


def first_stage_detections(
    detector, samples: list[Sample], cfg: RefineConfig, *, images: list[np.ndarray], progress: bool = False
) -> list[np.ndarray]:
    """``detector``'s detections scoring at least ``cfg.negative_score`` on each sample's image; a file
    listed more than once (a repeated supplement) is run once and its answer shared."""
    from rebar_data.perception.evaluation.evaluate import predict

    first: dict[str, int] = {}  # each file's first place in samples
    for i, s in enumerate(samples):
        first.setdefault(str(s.path), i)
    kept = list(first.values())
    ran = predict(
        detector,
        [samples[i] for i in kept],
        threshold=cfg.negative_score,
        images=[images[i] for i in kept],
        progress=progress,
    )
    of_file = {str(samples[i].path): p for i, p in zip(kept, ran, strict=True)}
    return [of_file[str(s.path)] for s in samples]


def with_lower_mat(
    samples: list[Sample], mined: list[np.ndarray], count: int, *, gate_px: float, seed: int
) -> list[np.ndarray]:
    """Each sample's mined negatives and up to ``count`` of the crossings its lower mat shows
    (:mod:`~rebar_data.perception.evaluation.lower_mat`), drawn at random for each listing of an image, those within
    ``gate_px`` of a visible crossing left out."""
    if not count:
        return mined
    rng = np.random.default_rng(np.random.SeedSequence([seed, 4111]))
    out = []
    for s, m, uv in zip(samples, mined, lower_mat_of(samples), strict=True):
        if len(s.visible) and len(uv):
            gap = np.linalg.norm(uv[:, None, :] - s.visible[None, :, :], axis=2).min(axis=1)
            uv = uv[gap > gate_px]
        if len(uv) > count:
            uv = uv[rng.choice(len(uv), count, replace=False)]
        out.append(np.ascontiguousarray(np.concatenate([np.reshape(m, (-1, 2)), uv]), np.float64))
    return out


def train_refiner(
    samples: list[Sample],
    out: Path,
    cfg: RefineConfig,
    aug: AugmentConfig,
    *,
    seed: int,
    images: list[np.ndarray] | None = None,
    negatives_of: Callable[[list[Sample], list[np.ndarray]], list[np.ndarray]] | None = None,
    data: list[str] | None = None,
    progress: bool = False,
) -> tuple[PatchNet, list[dict[str, float]]]:
    """Train the refiner on the visible crossings of ``samples``; resumable per epoch.

    With ``cfg.verify``, ``negatives_of(samples, images)`` gives each sample's negatives ((M, 2) points, usually
    :func:`mine_negatives` with the trained first stage); it is called once, only when there is
    training to do, and its answer is kept in the checkpoint for a resumed run. Without it there are
    no negatives and the verification output learns from positives alone.

    ``out/refine_last.pt`` holds the weights, optimiser, the negatives and the epochs done with their
    losses after every epoch. A finished one with the same settings is returned as it is, without
    training. ``data`` names what it trains on beyond the run's own images (the second-stage
    supplements); a checkpoint trained on other such data is trained afresh.

    Returns:
        The trained network (eval mode) and one row per epoch (loss, mean offset error in px, seconds,
        and with ``verify`` how many patches it classed rightly, of positives and of negatives).
    """
    last = out / "refine_last.pt"
    want = _training_settings(cfg)
    if not any(len(s.visible) for s in samples):
        raise ConfigError(
            "the train split has no visible crossings; accepted: a dataset with labelled crossings"
        )
    torch.manual_seed(seed)
    net = build(cfg).to(memory_format=torch.channels_last)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    # the same settings: go on where it stopped (with the negatives it mined); otherwise train afresh
    data = data or []
    payload = resume_stage(last, net, opt, load=load, settings=_training_settings, want=want, data=data)
    history: list[dict[str, float]] = payload["history"] if payload else []
    negatives: list[np.ndarray] | None = payload.get("negatives") if payload else None
    if len(history) < cfg.epochs:  # otherwise a finished stage: kept as it is
        threads_before = torch.get_num_threads()
        torch.set_num_threads(cfg.threads)
        try:
            if negatives is None and cfg.verify and negatives_of is not None:
                if images is None:
                    images = read_images(samples)
                negatives = negatives_of(samples, images)
                if progress:
                    tqdm.write(
                        f"second stage: {sum(len(n) for n in negatives)} negatives mined from the first stage's "
                        f"detections on {len(samples)} training images, beside "
                        f"{sum(len(s.visible) for s in samples)} crossings",
                        file=sys.stderr,
                    )
            elif negatives is None:
                negatives = [np.zeros((0, 2)) for _ in samples]
            _epochs(
                net,
                opt,
                history,
                negatives,
                samples,
                images,
                out,
                cfg,
                aug,
                seed=seed,
                data=data,
                progress=progress,
            )
        finally:
            torch.set_num_threads(threads_before)
    return copy.deepcopy(net).to(memory_format=torch.contiguous_format).eval(), history


def _training_settings(cfg: RefineConfig) -> dict[str, Any]:
    """The settings a trained refiner depends on (not those that only shape the exported file)."""
    return cfg.model_dump(mode="json", exclude=EXPORT_ONLY)


def _epochs(
    net: PatchNet,
    opt: torch.optim.Optimizer,
    history: list[dict[str, float]],
    negatives: list[np.ndarray],
    samples: list[Sample],
    images: list[np.ndarray] | None,
    out: Path,
    cfg: RefineConfig,
    aug: AugmentConfig,
    *,
    seed: int,
    data: list[str],
    progress: bool,
) -> None:
    """Train the remaining epochs on the visible crossings of ``samples`` and each sample's negatives."""
    last = out / "refine_last.pt"
    steps = steps_per_epoch(samples, negatives, cfg)
    total = cfg.epochs * steps
    first = len(history) + 1
    batches = patch_batches(samples, negatives, cfg, aug, seed=seed, first=first, images=images)
    for epoch in range(first, cfg.epochs + 1):
        net.train()
        t0, loss_sum, err_sum = time.perf_counter(), 0.0, 0.0
        right = np.zeros(2)  # patches classed rightly: negatives, positives
        seen = np.zeros(2)
        bar = tqdm(
            range(steps),
            desc=f"refiner {epoch}/{cfg.epochs}",
            unit="batch",
            disable=not progress,
            leave=False,
            file=sys.stderr,
        )
        for b in bar:
            step = (epoch - 1) * steps + b
            for g in opt.param_groups:
                g["lr"] = learning_rate(step, total, cfg)
            patches, y, labelled, is_crossing = next(batches)
            x = patches.permute(0, 3, 1, 2).float().contiguous(memory_format=torch.channels_last)
            pred = net(x)
            offset = pred[labelled, :2]
            loss = (
                F.smooth_l1_loss(offset, y[labelled, :2], beta=cfg.loss_beta_px)
                if len(offset)
                else pred.sum() * 0.0  # a batch of negatives alone
            )
            if net.size and len(offset):  # the log box side, of the labelled crossings alone
                loss = loss + cfg.size_weight * F.smooth_l1_loss(pred[labelled, 3], y[labelled, 2], beta=0.1)
            if net.verify:
                logit = pred[:, 2]
                loss = loss + cfg.verify_weight * F.binary_cross_entropy_with_logits(
                    logit, is_crossing.float()
                )
                label = is_crossing.numpy().astype(np.int64)
                seen += np.bincount(label, minlength=2)
                right += np.bincount(label[((logit > 0) == is_crossing).numpy()], minlength=2)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            loss_sum += loss.item()
            if len(offset):
                err_sum += float((offset.detach() - y[labelled, :2]).norm(dim=1).mean())
            bar.set_postfix(loss=f"{loss.item():.3f}")
        row = {
            "epoch": epoch,
            "loss": loss_sum / steps,
            "mean_error_px": err_sum / steps,
            "seconds": time.perf_counter() - t0,
        }
        if net.verify:
            row["verify_negatives_right"] = right[0] / max(seen[0], 1.0)
            row["verify_positives_right"] = right[1] / max(seen[1], 1.0)
        history.append(row)
        if progress:
            checked = (
                f"; classed rightly: {row['verify_positives_right']:.1%} of crossings, "
                f"{row['verify_negatives_right']:.1%} of {sum(len(n) for n in negatives)} negatives"
                if net.verify
                else ""
            )
            tqdm.write(
                f"refiner epoch {epoch}/{cfg.epochs}: loss {loss_sum / steps:.4f}, "
                f"mean error {err_sum / steps:.2f} px on jittered training patches{checked}",
                file=sys.stderr,
            )
        save(
            last,
            net,
            cfg,
            optimizer=opt.state_dict(),
            history=history,
            negatives=negatives,
            data=data,
        )


def calibrated_on(dataset: str | None, supplements: list[dict[str, Any]]) -> list[str]:
    """What an int8 file's metadata says it was calibrated on: ``dataset``'s train split and each supplement
    (:func:`~rebar_data.perception.training.train.supplement_images`' records)."""
    return [f"{dataset} train"] + [f"{m['name']} v{m['version']}" for m in supplements]
