"""Training and model files of the detector's third stage (:mod:`rebar_data.perception.inference.checks`).

It trains on depth patches around the training images' visible crossings (positives) and around the
places where the trained first stage finds crossings that are not there (negatives, the second stage's
mined ones: :func:`~rebar_data.perception.training.refine.mine_negatives`).
"""

from __future__ import annotations

import copy
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import Sample, read_depth
from rebar_data.perception.inference.checks import MM_PER_M, encode
from rebar_data.perception.networks.files import read_checkpoint
from rebar_data.perception.networks.stages import DepthNet
from rebar_data.perception.training.checkpoints import (
    fit_weights,
    resume_stage,
    save_stage,
)
from rebar_data.perception.training.config import DepthCheckConfig
from rebar_data.perception.training.schedule import warmup_cosine

FORMAT = "rebar-keypoint-depth-check"
FORMAT_VERSION = 1
EXPORT_ONLY = {"power", "threads"}  # settings that leave training alone
CHECKPOINT = "depth_last.pt"


def build(cfg: DepthCheckConfig) -> DepthNet:
    """The network these settings describe."""
    return DepthNet(cfg.patch_px, cfg.widths, cfg.hidden)


def save(path: Path, net: DepthNet, cfg: DepthCheckConfig, **extra: Any) -> None:
    save_stage(
        path, fmt=FORMAT, version=FORMAT_VERSION, config_key="depth_check_config", cfg=cfg, net=net, **extra
    )


def load(path: str | Path) -> tuple[DepthNet, DepthCheckConfig, dict[str, Any]]:
    """Rebuild the network from its ``.pt`` file: (network in eval mode, its settings, the whole payload)."""
    payload = read_checkpoint(path, fmt=FORMAT, what="depth-check")
    cfg = DepthCheckConfig.model_validate(payload["depth_check_config"])
    return fit_weights(build(cfg), payload, path), cfg, payload


def check_depth(samples: list[Sample]) -> None:
    """Raise ConfigError unless every sample has its depth image."""
    missing = [s for s in samples if s.depth_path is None]
    if missing:
        raise ConfigError(
            f"{missing[0].path}: has no depth image beside it ({len(missing)} of {len(samples)} training images "
            "lack one); accepted: a dataset with its depth/ folder, or depth_check: {enabled: false}"
        )


class PaddedDepth:
    """A depth image kept as uint16 millimetres, mirrored beyond its border once, so that a patch is a
    slice: ``patch(centre)`` equals :func:`~rebar_data.perception.inference.refine.patches`' cut (in metres) without
    padding the whole image for every patch."""

    def __init__(self, depth_m: np.ndarray, size: int):
        half = size // 2
        self.size = size
        self.height, self.width = depth_m.shape
        mm = np.clip(np.rint(depth_m * MM_PER_M), 0, 65535).astype(np.uint16)
        self._padded = cv2.copyMakeBorder(mm, half, half, half, half, cv2.BORDER_REFLECT)

    def patch(self, centre: np.ndarray) -> np.ndarray:
        u, v = np.clip(np.floor(np.asarray(centre, float) + 0.5), 0, [self.width, self.height]).astype(int)
        return self._padded[v : v + self.size, u : u + self.size].astype(np.float32) / MM_PER_M


def patch_batches(
    depths: list[PaddedDepth],
    samples: list[Sample],
    negatives: list[np.ndarray],
    cfg: DepthCheckConfig,
    *,
    seed: int,
    first: int,
) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """Every batch of epochs ``first`` to ``cfg.epochs``: encoded patches (B, 2, P, P) and whether each
    shows a crossing (B,). Each epoch's from a generator seeded by (seed, epoch) alone."""
    keys = np.array(
        [(i, k, 1) for i, s in enumerate(samples) for k in range(len(s.visible))]
        + [(i, k, 0) for i, n in enumerate(negatives) for k in range(len(n))],
        np.int64,
    ).reshape(-1, 3)
    steps = -(-len(keys) // cfg.batch_size)
    for epoch in range(first, cfg.epochs + 1):
        rng = np.random.default_rng(np.random.SeedSequence([seed, 7927, epoch]))
        order = rng.permutation(len(keys))
        for b in range(steps):
            rows = keys[order[b * cfg.batch_size : (b + 1) * cfg.batch_size]]
            jitter = rng.normal(0.0, cfg.jitter_px, (len(rows), 2))
            cut = np.empty((len(rows), cfg.patch_px, cfg.patch_px), np.float32)
            for j, (i, k, positive) in enumerate(rows):
                centre = samples[i].visible[k] if positive else negatives[i][k]
                cut[j] = depths[i].patch(centre + jitter[j])
            turns = rng.integers(0, 4, len(rows))
            flips = rng.uniform(size=len(rows)) < 0.5
            for t in range(1, 4):
                cut[turns == t] = np.rot90(cut[turns == t], t, axes=(1, 2))
            cut[flips] = cut[flips][:, :, ::-1]
            x, _ = encode(cut, scale_m=cfg.scale_m, clip=cfg.clip, gain=rng.uniform(*cfg.gain, len(rows)))
            yield torch.from_numpy(x), torch.from_numpy(rows[:, 2].astype(np.float32))


def train_depth_check(
    samples: list[Sample],
    negatives: list[np.ndarray] | Callable[[], list[np.ndarray]],
    out: Path,
    cfg: DepthCheckConfig,
    *,
    seed: int,
    data: list[str] | None = None,
    progress: bool = False,
) -> tuple[DepthNet, list[dict[str, float]]]:
    """Train the third stage on the depth images of ``samples``; resumable per epoch.

    ``out/depth_last.pt`` holds the weights, optimiser and the epochs done after every epoch; a finished
    one with the same settings and ``data`` (what its negatives came from, as the caller names it) is
    returned as it is. ``negatives`` (each sample's (M, 2) points) may be a function that gives them, called
    only when there is training to do.

    Returns:
        The trained network (eval mode) and one row per epoch (loss, the share of patches classed
        rightly among crossings and among negatives, seconds).
    """
    check_depth(samples)
    last = out / CHECKPOINT
    torch.manual_seed(seed)
    net = build(cfg)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    payload = resume_stage(last, net, opt, load=load, settings=_settings, want=_settings(cfg), data=data)
    history: list[dict[str, float]] = payload["history"] if payload else []
    if len(history) >= cfg.epochs:
        return net.eval(), history
    threads_before = torch.get_num_threads()
    torch.set_num_threads(cfg.threads)
    try:
        if callable(negatives):
            negatives = negatives()
        depths = [
            PaddedDepth(read_depth(s.depth_path), cfg.patch_px)
            for s in tqdm(samples, desc="depth images", disable=not progress, leave=False, file=sys.stderr)
        ]
        rows = sum(len(s.visible) for s in samples) + sum(len(n) for n in negatives)
        steps = -(-rows // cfg.batch_size)
        total = cfg.epochs * steps
        first = len(history) + 1
        batches = patch_batches(depths, samples, negatives, cfg, seed=seed, first=first)
        for epoch in range(first, cfg.epochs + 1):
            net.train()
            t0, loss_sum = time.perf_counter(), 0.0
            right, seen = np.zeros(2), np.zeros(2)
            bar = tqdm(
                range(steps),
                desc=f"depth check {epoch}/{cfg.epochs}",
                unit="batch",
                disable=not progress,
                leave=False,
                file=sys.stderr,
            )
            for b in bar:
                step = (epoch - 1) * steps + b
                for g in opt.param_groups:
                    g["lr"] = warmup_cosine(step, peak=cfg.lr, warm=max(1, round(0.03 * total)), total=total)
                x, y = next(batches)
                logit = net(x)
                loss = F.binary_cross_entropy_with_logits(logit, y)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                loss_sum += loss.item()
                label = y.numpy().astype(np.int64)
                seen += np.bincount(label, minlength=2)
                right += np.bincount(label[((logit.detach() > 0).float() == y).numpy()], minlength=2)
                bar.set_postfix(loss=f"{loss.item():.3f}")
            row = {
                "epoch": epoch,
                "loss": loss_sum / steps,
                "negatives_right": right[0] / max(seen[0], 1.0),
                "positives_right": right[1] / max(seen[1], 1.0),
                "seconds": time.perf_counter() - t0,
            }
            history.append(row)
            if progress:
                tqdm.write(
                    f"depth check epoch {epoch}/{cfg.epochs}: loss {row['loss']:.4f}; classed rightly: "
                    f"{row['positives_right']:.1%} of crossings, {row['negatives_right']:.1%} of negatives",
                    file=sys.stderr,
                )
            save(last, net, cfg, optimizer=opt.state_dict(), history=history, data=data or [])
    finally:
        torch.set_num_threads(threads_before)
    return copy.deepcopy(net).eval(), history


def _settings(cfg: DepthCheckConfig) -> dict[str, Any]:
    return cfg.model_dump(mode="json", exclude=EXPORT_ONLY)
