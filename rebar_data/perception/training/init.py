"""Training that starts from a model you have (``rebar train --init [MODEL]``, the shipped one by default).

A model's ONNX files hold every weight of its stages (the batch norms folded into the convolutions), so each
stage is read back into its network from them (:func:`~.files.weights_from_onnx`) and nothing else needs
shipping: a fresh clone fine-tunes the shipped model. The stages named by ``--stages`` train on from those
weights, their batch norms frozen, for :class:`~.config.InitConfig`'s epochs; the others are kept as the model
has them, their files copied byte for byte. The operating point (the score bias) and the line check, which
read the RGB stages' scores, are placed again on the validation split whenever the first or the second stage
changed; otherwise the model's are kept."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torch import nn

from rebar_data.config import ConfigError
from rebar_data.digest import sha256_file
from rebar_data.perception.inference import model_file
from rebar_data.perception.networks.files import network_from_onnx, weights_from_onnx
from rebar_data.perception.networks.keypoint_net import KeypointNet
from rebar_data.perception.training.config import TrainConfig, resolve_config

# what --stages names, in the order they train
STAGE_NAMES = ("first", "refine", "depth_check", "crossing_point")
# each later stage: its meta entry and the function naming its file beside the first stage's
LATER = {
    "refine": ("refiner", model_file.refiner_path),
    "depth_check": ("depth_check", model_file.depth_check_path),
    "crossing_point": ("crossing_point", model_file.crossing_point_path),
}
# what the operating point and the line check read: a change to these places them again
SCORING_STAGES = frozenset({"first", "refine"})


@dataclass
class InitModel:
    """A model read back for training: its first stage's file, meta and network, each later stage's network
    and file (by stage name), and the settings it was trained with."""

    path: Path
    sha256: str
    meta: dict[str, Any]
    first: KeypointNet
    stages: dict[str, nn.Module]
    files: dict[str, Path]
    trained_with: TrainConfig

    @property
    def source(self) -> str:
        """What a run records of where its weights came from."""
        return f"{self.path.name} sha256 {self.sha256[:16]}"

    def record(self, stages: Sequence[str]) -> dict[str, Any]:
        """The run's record of its start: the model file, its SHA-256 and the stages trained on."""
        return {"model": str(self.path), "sha256": self.sha256, "stages": list(stages)}


def parse_stages(text: str | Sequence[str] | None) -> tuple[str, ...]:
    """``--stages`` as the stage names it lists, in training order (None: every stage); ConfigError for a
    name that is not a stage."""
    if text is None:
        return STAGE_NAMES
    names = [n.strip() for n in (text.split(",") if isinstance(text, str) else text) if n.strip()]
    bad = [n for n in names if n not in STAGE_NAMES]
    if bad or not names:
        raise ConfigError(
            f"--stages {','.join(names) or repr(text)} is not accepted; accepted: a comma-separated list of "
            f"{', '.join(STAGE_NAMES)}"
        )
    return tuple(n for n in STAGE_NAMES if n in names)


def read_model(path: str | Path | None) -> InitModel:
    """The model at ``path`` (None: the shipped one; a run folder: its best model) read back for training.
    ConfigError unless it is an ONNX model written by ``rebar train`` with its stages beside it."""
    from rebar_data.perception.inference.detector import resolve_model_path
    from rebar_data.perception.training import crossing_point, depth_check, refine

    p = resolve_model_path(path)
    if p.suffix != ".onnx":
        raise ConfigError(
            f"{p}: --init reads a model's .onnx file; accepted: a model's .onnx file (a run's best.onnx, or "
            "the shipped model when none is named)"
        )
    first, meta = network_from_onnx(p)
    trained_with = resolve_config(meta.get("train_config"), {}, source=f"{p}'s train settings")
    builders = {
        "refine": refine.build,
        "depth_check": depth_check.build,
        "crossing_point": crossing_point.build,
    }
    entries = model_file.stage_entries(p, meta)  # checks each named file is there with its SHA-256
    stages: dict[str, nn.Module] = {}
    files: dict[str, Path] = {}
    for name, (entry, _) in LATER.items():
        if entry in entries:
            files[name] = entries[entry][0]
            stages[name] = weights_from_onnx(builders[name](getattr(trained_with, name)), files[name])
    int8 = model_file.int8_passes_path(p)
    if "refine" in files and meta.get("refiner", {}).get("int8_sha256") and int8.exists():
        files["int8"] = int8
    return InitModel(p, sha256_file(p), meta, first, stages, files, trained_with)


def settings_from(model: InitModel, settings: dict[str, Any] | None, *, source: str) -> TrainConfig:
    """The run's settings: those the model was trained with (so that each network's shape fits its weights),
    with ``settings`` (a ``--config`` file's) laid over them, section by section."""
    base = model.trained_with.model_dump(mode="json")
    for key, value in (settings or {}).items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            base[key] = {**base[key], **value}
        else:
            base[key] = value
    return resolve_config(base, {}, source=source)


def first_stage_settings(cfg: TrainConfig) -> TrainConfig:
    """The first stage's epochs from trained weights: ``cfg.init``'s epochs, learning rate and warm-up, no
    mosaics (the weights already know the scene; mosaics are for the first epochs from nothing)."""
    i = cfg.init
    augment = cfg.augment.model_copy(update={"mosaic_epochs": 0})
    return cfg.model_copy(
        update={"epochs": i.epochs, "lr": i.lr, "warmup_epochs": i.warmup_epochs, "augment": augment}
    )


def stage_settings(cfg: TrainConfig, name: str):
    """A later stage's settings for its epochs from trained weights: ``cfg.init.stage_epochs`` epochs at its
    own peak learning rate times ``cfg.init.stage_lr_scale``."""
    own = getattr(cfg, name)
    return own.model_copy(update={"epochs": cfg.init.stage_epochs, "lr": own.lr * cfg.init.stage_lr_scale})
