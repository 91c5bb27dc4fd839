"""What the later stages' training shares: their checkpoints, resuming from one, and the epoch loop."""

from __future__ import annotations

import copy
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from rebar_data.config import ConfigError
from rebar_data.perception.networks.files import write_checkpoint
from rebar_data.perception.training.epochs import warmup_cosine


def save_stage(
    path: Path, *, fmt: str, version: int, config_key: str, cfg, net: nn.Module, **extra: Any
) -> None:
    """Write a stage's checkpoint: its format, settings (under ``config_key``), weights and ``extra``."""
    payload = {"format": fmt, "format_version": version, config_key: cfg.model_dump(mode="json")}
    write_checkpoint(path, {**payload, "state_dict": net.state_dict(), **extra})


def fit_weights(net: nn.Module, payload: dict[str, Any], path: str | Path, *, retrain: str = "") -> nn.Module:
    """``net`` with the payload's weights, in eval mode; ConfigError when they do not fit its settings."""
    try:
        net.load_state_dict(payload["state_dict"])
    except RuntimeError:
        raise ConfigError(
            f"{path}: its weights do not fit the network its settings describe; accepted: a file written "
            f"by this version of `rebar train`{retrain}"
        ) from None
    return net.eval()


def train_stage(
    net: nn.Module,
    cfg,
    last: Path,
    *,
    name: str,
    load: Callable[[Path], tuple[nn.Module, Any, dict[str, Any]]],
    save: Callable[..., None],
    settings: Callable[[Any], dict[str, Any]],
    data: list[str] | None,
    prepare: Callable[[dict[str, Any] | None, int], tuple[Iterator, int, dict[str, Any]]],
    loss: Callable[[nn.Module, Any, dict[str, Any]], torch.Tensor],
    summary: Callable[[dict[str, Any], int], dict[str, float]],
    describe: Callable[[dict[str, float]], str],
    progress: bool,
) -> tuple[nn.Module, list[dict[str, float]]]:
    """Train ``net`` for ``cfg.epochs``, resumable per epoch from ``last``; returns it (eval mode) and a row
    per epoch.

    ``last`` holds the weights, optimiser, history and ``data`` (what it trained on beyond the run's own
    images) after every epoch; one with the same ``settings`` and ``data`` goes on where it stopped, a
    finished one is kept as it is. ``prepare(payload, first)`` runs only when there is training to do and
    gives the batches from epoch ``first`` on, the steps an epoch and what else the checkpoint keeps;
    ``loss`` adds to an epoch's tally, from which ``summary`` makes its row and ``describe`` its log line.
    """
    data = data or []
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    payload = None
    if last.exists():
        try:
            _, saved, payload = load(last)
        except ConfigError:  # an older layout: trained afresh
            payload = None
    if payload is not None and settings(saved) == settings(cfg) and payload.get("data", []) == data:
        net.load_state_dict(payload["state_dict"])
        opt.load_state_dict(payload["optimizer"])
    else:
        payload = None
    history: list[dict[str, float]] = payload["history"] if payload else []
    first = len(history) + 1
    threads_before = torch.get_num_threads()
    torch.set_num_threads(cfg.threads)
    try:
        batches, steps, keep = prepare(payload, first) if first <= cfg.epochs else (None, 0, {})
        total = cfg.epochs * steps
        for epoch in range(first, cfg.epochs + 1):
            net.train()
            t0, tally = time.perf_counter(), defaultdict(float)
            bar = tqdm(
                range(steps),
                desc=f"{name} {epoch}/{cfg.epochs}",
                unit="batch",
                disable=not progress,
                leave=False,
                file=sys.stderr,
            )
            for b in bar:
                lr = warmup_cosine(
                    (epoch - 1) * steps + b, peak=cfg.lr, warm=max(1, round(0.03 * total)), total=total
                )
                for g in opt.param_groups:
                    g["lr"] = lr
                x = loss(net, next(batches), tally)
                opt.zero_grad(set_to_none=True)
                x.backward()
                opt.step()
                tally["loss"] += x.item()
                bar.set_postfix(loss=f"{x.item():.3f}")
            history.append({"epoch": epoch, **summary(tally, steps), "seconds": time.perf_counter() - t0})
            if progress:
                tqdm.write(f"{name} epoch {epoch}/{cfg.epochs}: {describe(history[-1])}", file=sys.stderr)
            save(last, net, cfg, optimizer=opt.state_dict(), history=history, data=data, **keep)
    finally:
        torch.set_num_threads(threads_before)
    return copy.deepcopy(net).to(memory_format=torch.contiguous_format).eval(), history


def count_classes(tally: dict[str, Any], logit: torch.Tensor, truth: torch.Tensor) -> None:
    """Add to an epoch's tally how many patches of each class (no crossing, crossing) ``logit`` classed
    rightly (``right``) of how many it saw (``seen``)."""
    label = truth.numpy().astype(np.int64)
    tally["seen"] += np.bincount(label, minlength=2)
    tally["right"] += np.bincount(label[((logit.detach() > 0) == truth).numpy()], minlength=2)


def classed_rightly(tally: dict[str, Any]) -> tuple[float, float]:
    """The shares of negatives and of crossings classed rightly in an epoch's tally."""
    right, seen = tally["right"], tally["seen"]
    return right[0] / max(seen[0], 1.0), right[1] / max(seen[1], 1.0)
