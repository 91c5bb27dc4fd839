"""What one call of ``rebar train`` works on (:class:`TrainRun`), as its training and its shipping steps
(:mod:`.ship`) read it, and the keys those steps compare."""

from __future__ import annotations

import hashlib
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from rebar_data.perception.evaluation.data import Sample
from rebar_data.perception.training.config import TrainConfig
from rebar_data.perception.training.init import STAGE_NAMES, InitModel
from rebar_data.resume import Steps


@dataclass
class TrainRun:
    """What one call of :func:`~.train.train` works on."""

    cfg: TrainConfig
    out: Path
    sigma: float
    dataset: dict[str, Any]  # what the run records of its data
    train: list[Sample]
    val: list[Sample]
    test: list[Sample]
    refine_extra: list[Sample]
    line_extra: list[Sample]
    line_supplements: list[dict[str, Any]]
    progress: bool
    init: InitModel | None = None  # the model whose weights the run starts from (--init)
    steps: Steps | None = None  # the finishing steps done (steps.json)
    device: torch.device = torch.device("cpu")  # where the networks train
    stages: tuple[str, ...] = STAGE_NAMES  # the stages it trains; the others are the init model's
    started: float = 0.0  # when the first stage's epochs began
    train_seconds: float = 0.0  # from then until the later stages were trained

    def log(self, msg: str) -> None:
        if self.progress:
            tqdm.write(msg, file=sys.stderr)

    def trains(self, stage: str) -> bool:
        """Whether the run trains ``stage`` (one of :data:`~.init.STAGE_NAMES`) rather than keep the init
        model's."""
        return stage in self.stages

    def kept(self, stage: str) -> bool:
        """Whether ``stage`` is the init model's, kept as it is."""
        return (
            self.init is not None
            and not self.trains(stage)
            and (stage == "first" or stage in self.init.stages)
        )

    @property
    def init_record(self) -> dict[str, Any] | None:
        return None if self.init is None else self.init.record(self.stages)


def supplement_names(supplements: list[dict[str, Any]]) -> list[str]:
    """Supplements as a run compares them: name and version of each."""
    return [f"{d.get('name')} v{d.get('version')}" for d in supplements]


def weights_key(net: torch.nn.Module) -> str:
    """The SHA-256 of a network's weights (what a step that runs it depends on)."""
    h = hashlib.sha256()
    for k, v in sorted(net.state_dict().items()):
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()
