"""What the later stages' training shares: their checkpoints (written and read through
:mod:`rebar_data.perception.networks.files`), resuming from one, and the points that calibrate an int8 file."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import Sample
from rebar_data.perception.networks.files import write_checkpoint


def save_stage(
    path: Path, *, fmt: str, version: int, config_key: str, cfg, net: nn.Module, **extra: Any
) -> None:
    """Write a stage's checkpoint atomically: its format, settings (under ``config_key``), weights and
    ``extra`` (training state)."""
    write_checkpoint(
        path,
        {
            "format": fmt,
            "format_version": version,
            config_key: cfg.model_dump(mode="json"),
            "state_dict": net.state_dict(),
            **extra,
        },
    )


def resume_stage(
    path: Path,
    net: nn.Module,
    opt: torch.optim.Optimizer,
    *,
    load: Callable[[Path], tuple[nn.Module, Any, dict[str, Any]]],
    settings: Callable[[Any], dict[str, Any]],
    want: dict[str, Any],
    data: list[str] | None = None,
) -> dict[str, Any] | None:
    """Go on where a stage's checkpoint at ``path`` stopped: when it holds a run with the training settings
    ``want`` (``settings`` of its saved config), its weights and optimiser state go into ``net`` and
    ``opt`` and its payload is returned (``history``, and what else the stage keeps); None, to train
    afresh, when there is none, it cannot be read (an older layout), its settings differ or it trained on
    other data than ``data`` names (what the stage's checkpoint records under ``data``; none is an empty
    list). ``load`` is the stage's own reader."""
    if not path.exists():
        return None
    try:
        _, saved, payload = load(path)
    except ConfigError:
        return None
    if settings(saved) != want or payload.get("data", []) != (data or []):
        return None
    net.load_state_dict(payload["state_dict"])
    opt.load_state_dict(payload["optimizer"])
    return payload


def fit_weights(net: nn.Module, payload: dict[str, Any], path: str | Path, *, retrain: str = "") -> nn.Module:
    """``net`` with the payload's weights, in eval mode; ConfigError when they are of another shape than
    its settings describe (an older layout). ``retrain`` is appended to the message (what to train again)."""
    try:
        net.load_state_dict(payload["state_dict"])
    except RuntimeError:
        raise ConfigError(
            f"{path}: its weights do not fit the network its settings describe; accepted: a file written "
            f"by this version of `rebar train`{retrain}"
        ) from None
    return net.eval()


def calibration_points(
    samples: list[Sample], *, count: int, jitter_px: float, rng: np.random.Generator, images_used: int = 64
) -> Iterator[tuple[Sample, np.ndarray]]:
    """Points as a stage meets them at inference, to set an int8 file's value ranges: visible crossings of
    an even spread of ``images_used`` of ``samples``, about ``count`` in all, each moved by a Gaussian
    error of ``jitter_px``. Yields (sample, (M, 2) points)."""
    used = [s for s in samples if len(s.visible)]
    used = [
        used[i] for i in np.unique(np.linspace(0, len(used) - 1, min(images_used, len(used))).astype(int))
    ]
    each = -(-count // max(1, len(used)))
    for s in used:
        pick = rng.choice(len(s.visible), size=min(each, len(s.visible)), replace=False)
        yield s, s.visible[pick] + rng.normal(0.0, jitter_px, (len(pick), 2))
