"""What the later stages' training shares: their checkpoints, resuming from one, and the epoch loop."""

from __future__ import annotations

import copy
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from rebar_data.config import ConfigError
from rebar_data.perception.networks.files import read_checkpoint, write_checkpoint
from rebar_data.perception.training.epochs import batch_bar, warmup_cosine


@dataclass(frozen=True)
class StageFile:
    """A later stage's ``.pt`` file: its format, its settings (class, key) and the network they build."""

    fmt: str
    what: str  # the stage, in an error
    config: type
    config_key: str
    build: Callable[[Any], nn.Module]
    export_only: frozenset[str] = frozenset()  # settings that leave training alone
    defaults: tuple[tuple[str, Any], ...] = ()  # settings of files written before them
    retrain: str = ""  # what to train again, in an error

    def save(self, path: Path, net: nn.Module, cfg, **extra: Any) -> None:
        """Write the stage's format, settings, weights and ``extra`` (training state)."""
        head = {"format": self.fmt, "format_version": 1, self.config_key: cfg.model_dump(mode="json")}
        write_checkpoint(path, {**head, "state_dict": net.state_dict(), **extra})

    def load(self, path: str | Path) -> tuple[nn.Module, Any, dict[str, Any]]:
        """Rebuild the network from its file: (network in eval mode, its settings, the whole payload)."""
        payload = read_checkpoint(path, fmt=self.fmt, what=self.what)
        cfg = self.config.model_validate({**dict(self.defaults), **payload[self.config_key]})
        net = self.build(cfg)
        try:
            net.load_state_dict(payload["state_dict"])
        except RuntimeError:
            raise ConfigError(
                f"{path}: its weights do not fit the network its settings describe; accepted: a file written "
                f"by this version of `rebar train`{self.retrain}"
            ) from None
        return net.eval(), cfg, payload

    def settings(self, cfg) -> dict[str, Any]:
        """The settings a trained stage depends on."""
        return cfg.model_dump(mode="json", exclude=set(self.export_only))


def train_stage(
    stage: StageFile,
    net: nn.Module,
    cfg,
    last: Path,
    *,
    name: str,
    data: list[str] | None,
    prepare: Callable[[dict[str, Any] | None, int], tuple[Iterator, int, dict[str, Any]]],
    loss: Callable[[nn.Module, Any, dict[str, Any]], torch.Tensor],
    summary: Callable[[dict[str, Any], int], dict[str, float]],
    describe: Callable[[dict[str, float]], str],
    progress: bool,
    init: nn.Module | None = None,
    device: torch.device | str = "cpu",
) -> tuple[nn.Module, list[dict[str, float]]]:
    """Train ``net`` for ``cfg.epochs``; returns it (eval mode) and a row per epoch. ``last`` is saved after
    every epoch; one with the same training settings and ``data`` (what it trained on beyond the run's own
    images) goes on where it stopped. ``prepare(payload, first)`` gives the batches from epoch ``first`` on,
    the steps an epoch and what else the checkpoint keeps; ``loss`` adds to an epoch's tally, from which
    ``summary`` makes its row and ``describe`` its log line. ``init``: a trained network of the same shape
    whose weights ``net`` starts from (say so in ``data``), its batch norms then frozen. It trains on
    ``device``, each batch's tensors moved there."""
    data = data or []
    if init is not None:
        net.load_state_dict(init.state_dict())
    net = net.to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    payload = None
    if last.exists():
        with suppress(ConfigError):  # an older layout: trained afresh
            _, saved, payload = stage.load(last)
    same = payload is not None and stage.settings(saved) == stage.settings(cfg)
    if same and payload.get("data", []) == data:
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
        warm = max(1, round(0.03 * total))
        for epoch in range(first, cfg.epochs + 1):
            net.train()
            for m in net.modules() if init is not None else ():
                if isinstance(m, nn.modules.batchnorm._BatchNorm):
                    m.eval()  # trained weights: their batch norms keep what they learned
            t0, tally = time.perf_counter(), defaultdict(float)
            bar = batch_bar(steps, f"{name} {epoch}/{cfg.epochs}", progress=progress)
            for b in bar:
                lr = warmup_cosine((epoch - 1) * steps + b, peak=cfg.lr, warm=warm, total=total)
                for g in opt.param_groups:
                    g["lr"] = lr
                x = loss(net, tuple(t.to(device, non_blocking=True) for t in next(batches)), tally)
                opt.zero_grad(set_to_none=True)
                x.backward()
                opt.step()
                tally["loss"] += x.item()
                bar.set_postfix(loss=f"{x.item():.3f}")
            history.append({"epoch": epoch, **summary(tally, steps), "seconds": time.perf_counter() - t0})
            if progress:
                tqdm.write(f"{name} epoch {epoch}/{cfg.epochs}: {describe(history[-1])}", file=sys.stderr)
            stage.save(last, net, cfg, optimizer=opt.state_dict(), history=history, data=data, **keep)
    finally:
        torch.set_num_threads(threads_before)
    return copy.deepcopy(net).cpu().to(memory_format=torch.contiguous_format).eval(), history


def count_classes(tally: dict[str, Any], logit: torch.Tensor, truth: torch.Tensor) -> None:
    """Add to an epoch's tally how many patches of each class (no crossing, crossing) ``logit`` classed
    rightly (``right``) of how many it saw (``seen``)."""
    label = truth.cpu().numpy().astype(np.int64)
    tally["seen"] += np.bincount(label, minlength=2)
    tally["right"] += np.bincount(label[((logit.detach() > 0) == truth).cpu().numpy()], minlength=2)


def classed_rightly(tally: dict[str, Any]) -> tuple[float, float]:
    """The shares of negatives and of crossings classed rightly in an epoch's tally."""
    right, seen = tally["right"], tally["seen"]
    return right[0] / max(seen[0], 1.0), right[1] / max(seen[1], 1.0)
