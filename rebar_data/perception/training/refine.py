"""Training and model files of the detector's second stage (:mod:`rebar_data.perception.inference.refine`).

It trains from the labels alone, on jittered, turned, flipped and scaled patches around the training
images' visible crossings (:mod:`~rebar_data.perception.training.refine_data`), so it never learns one
first-stage network's quirks; only its verification output looks at the first stage, whose false
detections are its negatives (:func:`negatives_in`)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import Sample, read_image, read_images
from rebar_data.perception.evaluation.lower_mat import lower_mat_of
from rebar_data.perception.networks.stages import PatchNet
from rebar_data.perception.training.config import AugmentConfig, RefineConfig
from rebar_data.perception.training.later_stages import StageFile, classed_rightly, count_classes, train_stage
from rebar_data.perception.training.refine_data import patch_batches, steps_per_epoch


def build(cfg: RefineConfig) -> PatchNet:
    """The refiner network these settings describe."""
    return PatchNet(cfg.patch_px, cfg.widths, cfg.hidden, cfg.blocks, verify=cfg.verify, size=cfg.size)


# the settings that leave training alone: how the file is written, and how the detector runs it
WRITING = ("quantize", "calibration_patches")
RUNNING = ("verify_power", "views", "first_pass_views", "iterations", "step", "shrink_above_px")
FILE = StageFile(
    "rebar-keypoint-refiner",
    "refiner",
    RefineConfig,
    "refine_config",
    build,
    export_only=frozenset(WRITING + RUNNING),
    defaults=(("verify", False), ("size", False)),  # files from before the stage could verify or size
    retrain=" (train the second stage again)",
)
save, load = FILE.save, FILE.load


def calibration_patches(samples: list[Sample], cfg: RefineConfig, *, seed: int) -> np.ndarray:
    """(``cfg.calibration_patches``, P, P, C) uint8 patches cut as at inference around jittered visible
    crossings of an even spread of 64 images, to set the int8 file's value ranges."""
    from rebar_data.perception.inference.refine import patches

    rng = np.random.default_rng(np.random.SeedSequence([seed, 4099]))
    used = [s for s in samples if len(s.visible)]
    spread = np.unique(np.linspace(0, len(used) - 1, min(64, len(used))).astype(int))
    used = [used[i] for i in spread]
    each = -(-cfg.calibration_patches // max(1, len(used)))
    out = []
    for s in used:
        pick = rng.choice(len(s.visible), size=min(each, len(s.visible)), replace=False)
        uv = s.visible[pick] + rng.normal(0.0, cfg.jitter_px, (len(pick), 2))
        out.append(patches(read_image(s.path), uv, cfg.patch_px, border="mask")[0])
    if not out:
        raise ConfigError(
            "no visible crossings to calibrate the int8 second stage on; accepted: quantize: none"
        )
    return np.concatenate(out)[: cfg.calibration_patches]


def negatives_in(found: list[np.ndarray], samples: list[Sample], cfg: RefineConfig) -> list[np.ndarray]:
    """Where the first stage finds crossings that are not there: per sample, (M, 2) u, v of its detections
    ``found`` (:func:`first_stage_detections`) farther than ``cfg.negative_gate_px`` from every crossing."""
    gate = cfg.negative_gate_px
    return [_away_from(s.visible, p[:, :2].reshape(-1, 2), gate) for s, p in zip(samples, found, strict=True)]


def _away_from(visible: np.ndarray, uv: np.ndarray, gate_px: float) -> np.ndarray:
    """The points ``uv`` farther than ``gate_px`` from every visible crossing, as float64."""
    if len(visible) and len(uv):
        uv = uv[np.linalg.norm(uv[:, None, :] - visible[None, :, :], axis=2).min(axis=1) > gate_px]
    return np.ascontiguousarray(uv, np.float64)


def first_stage_detections(
    detector, samples: list[Sample], cfg: RefineConfig, *, images: list[np.ndarray], progress: bool = False
) -> list[np.ndarray]:
    """``detector``'s detections scoring ``cfg.negative_score`` or more on each sample's image; a file
    listed more than once (a repeated supplement) is run once."""
    from rebar_data.perception.evaluation.evaluate import predict

    first: dict[str, int] = {}  # each file's first place in samples
    for i, s in enumerate(samples):
        first.setdefault(str(s.path), i)
    kept = list(first.values())
    kept_samples, kept_images = [samples[i] for i in kept], [images[i] for i in kept]
    ran = predict(detector, kept_samples, threshold=cfg.negative_score, images=kept_images, progress=progress)
    of_file = {str(samples[i].path): p for i, p in zip(kept, ran, strict=True)}
    return [of_file[str(s.path)] for s in samples]


def with_lower_mat(
    samples: list[Sample], mined: list[np.ndarray], count: int, *, gate_px: float, seed: int
) -> list[np.ndarray]:
    """Each sample's mined negatives and up to ``count`` of its lower mat's crossings (drawn at random for
    each listing of an image), those within ``gate_px`` of a visible crossing left out."""
    if not count:
        return mined
    rng = np.random.default_rng(np.random.SeedSequence([seed, 4111]))
    out = []
    for s, m, uv in zip(samples, mined, lower_mat_of(samples), strict=True):
        uv = _away_from(s.visible, uv, gate_px)
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
    init: PatchNet | None = None,
    device: torch.device | str = "cpu",
) -> tuple[PatchNet, list[dict[str, float]]]:
    """Train the refiner on the visible crossings of ``samples``, resumable in ``out/refine_last.pt``; returns
    it and one row per epoch. With ``cfg.verify``, ``negatives_of(samples, images)`` gives each sample's
    (M, 2) negatives (:func:`negatives_in`; called only when there is training to do, its answer kept in
    the checkpoint); without it the verification learns from positives alone. ``init``: trained weights to
    start from (:func:`~.later_stages.train_stage`)."""
    if not any(len(s.visible) for s in samples):
        raise ConfigError(
            "the train split has no visible crossings; accepted: a dataset with labelled crossings"
        )
    torch.manual_seed(seed)
    net = build(cfg).to(memory_format=torch.channels_last)
    negatives: list[np.ndarray] = []

    def prepare(payload, first):
        nonlocal images, negatives
        negatives = payload.get("negatives") if payload else None
        if negatives is None and cfg.verify and negatives_of is not None:
            images = read_images(samples) if images is None else images
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
        batches = patch_batches(samples, negatives, cfg, aug, seed=seed, first=first, images=images)
        return batches, steps_per_epoch(samples, negatives, cfg), {"negatives": negatives}

    def loss(net, batch, tally):
        patches, y, labelled, is_crossing = batch
        pred = net(patches.permute(0, 3, 1, 2).float().contiguous(memory_format=torch.channels_last))
        offset = pred[labelled, :2]
        if not len(offset):  # a batch of negatives alone
            total = pred.sum() * 0.0
        else:
            total = F.smooth_l1_loss(offset, y[labelled, :2], beta=cfg.loss_beta_px)
            tally["error"] += float((offset.detach() - y[labelled, :2]).norm(dim=1).mean())
            if net.size:  # the log box side, of the labelled crossings alone
                total = total + cfg.size_weight * F.smooth_l1_loss(
                    pred[labelled, 3], y[labelled, 2], beta=0.1
                )
        if net.verify:
            logit = pred[:, 2]
            total = total + cfg.verify_weight * F.binary_cross_entropy_with_logits(logit, is_crossing.float())
            count_classes(tally, logit, is_crossing)
        return total

    def summary(tally, steps):
        row = {"loss": tally["loss"] / steps, "mean_error_px": tally["error"] / steps}
        if net.verify:
            row["verify_negatives_right"], row["verify_positives_right"] = classed_rightly(tally)
        return row

    def describe(row):
        error = row["mean_error_px"]
        text = f"loss {row['loss']:.4f}, mean error {error:.2f} px on jittered training patches"
        if net.verify:
            text += f"; classed rightly: {row['verify_positives_right']:.1%} of crossings, "
            text += f"{row['verify_negatives_right']:.1%} of {sum(len(n) for n in negatives)} negatives"
        return text

    return train_stage(
        FILE,
        net,
        cfg,
        out / "refine_last.pt",
        name="refiner",
        data=data,
        prepare=prepare,
        loss=loss,
        summary=summary,
        describe=describe,
        progress=progress,
        init=init,
        device=device,
    )
