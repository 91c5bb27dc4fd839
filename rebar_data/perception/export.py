"""Model files: PyTorch checkpoints (weights + architecture + provenance) and ONNX exports for inference.

A ``.pt`` file is a dict with ``format``, ``model_config``, ``state_dict`` and ``meta``; training's own
checkpoints add the optimiser and progress so a run can resume. An ``.onnx`` file takes uint8 RGB
(1, H, W, 3) and returns the network's (1, 3, H/4, W/4) output; the same ``meta`` is stored in its
metadata under ``rebar_keypoint`` as JSON, so the one file says what it is, how it was trained and how
well it scored.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import torch

from rebar_data.config import ConfigError
from rebar_data.perception.config import ModelConfig
from rebar_data.perception.model import STRIDE, ExportWrapper, KeypointNet

FORMAT = "rebar-keypoint"
FORMAT_VERSION = 1
META_KEY = "rebar_keypoint"


def save_checkpoint(path: str | Path, net: KeypointNet, meta: dict[str, Any], **extra: Any) -> None:
    """Write weights, architecture and ``meta`` (plus any training state in ``extra``) atomically."""
    path = Path(path)
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "model_config": net.cfg.model_dump(mode="json"),
        "state_dict": net.state_dict(),
        "meta": meta,
        **extra,
    }
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)


def load_checkpoint(path: str | Path) -> tuple[KeypointNet, dict[str, Any], dict[str, Any]]:
    """Rebuild the network of a ``.pt`` file; returns (network in eval mode, meta, the whole payload)."""
    path = Path(path)
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # a truncated or foreign file: say which
        raise ConfigError(f"{path}: cannot be read as a detector checkpoint ({type(e).__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ConfigError(
            f"{path}: is not a {FORMAT} checkpoint; accepted: a .pt file written by `rebar train`"
        )
    if payload.get("format_version", 0) > FORMAT_VERSION:
        raise ConfigError(
            f"{path}: format_version {payload['format_version']} is newer than this code reads ({FORMAT_VERSION})"
        )
    net = KeypointNet(ModelConfig.model_validate(payload["model_config"]))
    net.load_state_dict(payload["state_dict"])
    net.eval()
    return net, payload.get("meta", {}), payload


def export_onnx(
    net: KeypointNet, path: str | Path, meta: dict[str, Any], *, example_hw: tuple[int, int] = (480, 640)
) -> Path:
    """Export the network to ONNX with dynamic image size and ``meta`` in the file's metadata."""
    import onnx

    path = Path(path)
    net = net.eval()
    inputs: tuple[torch.Tensor, ...] = (torch.zeros((1, *example_hw, 3), dtype=torch.uint8),)
    names = ["image"]
    axes = {"image": {1: "height", 2: "width"}, "output": {2: "cells_y", 3: "cells_x"}}
    if net.cfg.ray_channels:
        inputs += (
            torch.zeros((1, 2, example_hw[0] // STRIDE, example_hw[1] // STRIDE), dtype=torch.float32),
        )
        names.append("rays")
        axes["rays"] = {2: "cells_y", 3: "cells_x"}
    tmp = path.with_name(path.name + ".tmp")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            ExportWrapper(net),
            inputs,
            str(tmp),
            input_names=names,
            output_names=["output"],
            dynamic_axes=axes,
            opset_version=17,
            dynamo=False,
        )
    model = onnx.load(str(tmp))
    full = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "model_config": net.cfg.model_dump(mode="json"),
        **meta,
    }
    entry = model.metadata_props.add()
    entry.key, entry.value = META_KEY, json.dumps(full, sort_keys=True)
    onnx.save(model, str(tmp))
    tmp.replace(path)
    return path


def update_onnx_meta(path: str | Path, changes: dict[str, Any]) -> Path:
    """Rewrite the ``meta`` of an ONNX file from :func:`export_onnx` with ``changes`` merged in (atomically;
    the network is untouched)."""
    import onnx

    path = Path(path)
    model = onnx.load(str(path))
    entries = [e for e in model.metadata_props if e.key == META_KEY]
    if not entries:
        raise ConfigError(
            f"{path}: carries no detector metadata; accepted: a model file written by `rebar train`"
        )
    entries[0].value = json.dumps({**json.loads(entries[0].value), **changes}, sort_keys=True)
    tmp = path.with_name(path.name + ".tmp")
    onnx.save(model, str(tmp))
    tmp.replace(path)
    return path


def onnx_meta(path: str | Path) -> dict[str, Any]:
    """The ``meta`` stored in an ONNX file by :func:`export_onnx` (empty if it has none)."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    raw = sess.get_modelmeta().custom_metadata_map.get(META_KEY)
    return json.loads(raw) if raw else {}
