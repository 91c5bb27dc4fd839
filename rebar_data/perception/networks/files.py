"""Model files: PyTorch checkpoints (``format``, ``model_config``, ``state_dict``, ``meta`` and, for
training's own, its progress) and the ONNX files the run time reads, the first stage's with the same
``meta`` as JSON in its metadata (what it is, how it was trained, how well it scored)."""

from __future__ import annotations

import json
import logging
import pickle
import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from rebar_data.config import ConfigError
from rebar_data.outputs import replace_file
from rebar_data.perception.inference.detector import STRIDE
from rebar_data.perception.inference.model_file import FORMAT, FORMAT_VERSION, META_KEY, check_format
from rebar_data.perception.networks.keypoint_net import KeypointNet, ModelConfig, UInt8Input
from rebar_data.perception.networks.stages import CrossingNet, DepthNet, PatchNet


def write_checkpoint(path: str | Path, payload: dict[str, Any]) -> None:
    """Write a ``.pt`` checkpoint atomically (a temporary file renamed into place)."""
    replace_file(Path(path), lambda tmp: torch.save(payload, tmp))


def _data_types() -> list:
    """What a checkpoint may hold beside tensors and Python's plain types: numpy's scalars and arrays of numbers
    (training's history and mined points), rebuilt from their bytes by numpy's own constructors."""
    kept = ("ObjectDType", "VoidDType", "StringDType")  # these could carry objects: not data
    numeric = [getattr(np.dtypes, n) for n in dir(np.dtypes) if n.endswith("DType") and n not in kept]
    core = np._core.multiarray
    return [core.scalar, core._reconstruct, np.ndarray, np.dtype, bytes, *numeric]


def read_checkpoint(path: str | Path, *, fmt: str, what: str) -> dict[str, Any]:
    """A ``.pt`` checkpoint's payload; ConfigError when the file cannot be read or is not a ``fmt`` file.
    Read as data alone (``weights_only``: tensors, numbers, strings, lists, dicts, numpy arrays of numbers), so
    a file that would run code when unpickled is refused before anything in it runs."""
    path = Path(path)
    try:
        with torch.serialization.safe_globals(_data_types()):
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        # what the weights-only reader refused: a global (code, a class) or an object; else not a pickle at all
        if not re.search(r"global|can only build", str(e), re.IGNORECASE):
            raise ConfigError(f"{path}: cannot be read as a {what} checkpoint (UnpicklingError)") from None
        raise ConfigError(
            f"{path}: holds more than weights and numbers (code or objects a checkpoint never holds), so it is "
            f"not read; accepted: a {what} checkpoint written by `rebar train`"
        ) from None
    except Exception as e:  # a truncated or foreign file: say which
        raise ConfigError(f"{path}: cannot be read as a {what} checkpoint ({type(e).__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != fmt:
        raise ConfigError(f"{path}: is not a {fmt} checkpoint; accepted: a .pt file written by `rebar train`")
    return payload


def save_checkpoint(path: str | Path, net: KeypointNet, meta: dict[str, Any], **extra: Any) -> None:
    """Write the first stage's weights, architecture and ``meta`` (plus any training state in ``extra``)."""
    write_checkpoint(path, {**_head(net), "state_dict": net.state_dict(), "meta": meta, **extra})


def _head(net: KeypointNet) -> dict[str, Any]:
    """What a first-stage file says of itself: its format and version and the network's settings."""
    config = net.cfg.model_dump(mode="json")
    return {"format": FORMAT, "format_version": FORMAT_VERSION, "model_config": config}


def load_checkpoint(path: str | Path) -> tuple[KeypointNet, dict[str, Any], dict[str, Any]]:
    """Rebuild the network of a ``.pt`` file; returns (network in eval mode, meta, the whole payload)."""
    payload = check_format(read_checkpoint(path, fmt=FORMAT, what="detector"), Path(path))
    net = KeypointNet(ModelConfig.model_validate(payload["model_config"]))
    net.load_state_dict(payload["state_dict"])
    return net.eval(), payload.get("meta", {}), payload


def export_onnx(net: nn.Module, path: str | Path, meta: dict[str, Any] | None = None) -> Path:
    """Write any of the detector's networks as the ONNX file the run time reads (atomically): the first
    stage takes uint8 RGB (1, H, W, 3) and the cells' rays, any image size, ``meta`` in its metadata under
    :data:`META_KEY`; the later stages take a batch of patches (uint8, or the depth check's encoded float32)
    and carry no metadata (the first stage's names them)."""
    import onnx

    path = Path(path)
    net = net.eval()
    example_hw = (480, 640)  # the traced size; the image axes stay free
    if isinstance(net, KeypointNet):
        cells = (example_hw[0] // STRIDE, example_hw[1] // STRIDE)
        image, rays = torch.zeros((1, *example_hw, 3), dtype=torch.uint8), torch.zeros((1, 2, *cells))
        inputs: tuple[torch.Tensor, ...] = (image, rays)
        module, names, output = UInt8Input(net), ["image", "rays"], "output"
        grid = {2: "cells_y", 3: "cells_x"}
        axes = {"image": {1: "height", 2: "width"}, "output": grid, "rays": dict(grid)}
    else:
        size = net.patch_px
        if isinstance(net, PatchNet):
            module, names, output = UInt8Input(net), ["patches"], "offset"
            inputs = (torch.zeros((4, size, size, net.channels), dtype=torch.uint8),)
        elif isinstance(net, DepthNet):
            module, names, output = net, ["depth"], "logit"
            inputs = (torch.zeros((4, 2, size, size), dtype=torch.float32),)
        elif isinstance(net, CrossingNet):
            module, names, output = UInt8Input(net), ["patches", "rays"], "offset"
            inputs = (torch.zeros((4, size, size, 3), dtype=torch.uint8), torch.zeros((4, 2)))
        else:
            raise TypeError(f"{type(net).__name__} is not one of the detector's networks")
        axes = {**{n: {0: "n"} for n in names}, output: {0: "n"}}
    tmp = path.with_name(path.name + ".tmp")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module.eval(),
            inputs,
            str(tmp),
            input_names=names,
            output_names=[output],
            dynamic_axes=axes,
            opset_version=17,
            dynamo=False,
        )
    if isinstance(net, KeypointNet):
        model = onnx.load(str(tmp))
        entry = model.metadata_props.add()
        entry.key, entry.value = META_KEY, json.dumps({**_head(net), **(meta or {})}, sort_keys=True)
        onnx.save(model, str(tmp))
    tmp.replace(path)
    return path


def update_onnx_meta(path: str | Path, changes: dict[str, Any]) -> Path:
    """Merge ``changes`` into the ``meta`` of an ONNX file from :func:`export_onnx` (atomically)."""
    import onnx

    path = Path(path)
    model = onnx.load(str(path))
    entry = _meta_entry(model, path)
    entry.value = json.dumps({**json.loads(entry.value), **changes}, sort_keys=True)
    return replace_file(path, lambda tmp: onnx.save(model, str(tmp)))


def _meta_entry(model, path: Path):
    """The metadata entry of a loaded ONNX ``model`` (from ``path``) that holds the detector's meta."""
    for entry in model.metadata_props:
        if entry.key == META_KEY:
            return entry
    raise ConfigError(
        f"{path}: carries no detector metadata; accepted: a model file written by `rebar train`"
    )


def onnx_meta(path: str | Path) -> dict[str, Any]:
    """The ``meta`` stored in an ONNX file by :func:`export_onnx` (empty if it has none)."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    raw = sess.get_modelmeta().custom_metadata_map.get(META_KEY)
    return check_format(json.loads(raw) if raw else {}, Path(path))


def check_model_file(model: str | Path) -> Path:
    """``model`` as a Path once it is an ONNX file written by ``rebar train``; ConfigError otherwise."""
    model = Path(model)
    if model.suffix != ".onnx" or not model.exists():
        raise ConfigError(
            f"{model}: no such ONNX model; accepted: a detector's .onnx file, such as best.onnx"
        )
    if not onnx_meta(model):
        raise ConfigError(
            f"{model}: carries no detector metadata; accepted: a model file written by `rebar train`"
        )
    return model


def _read_onnx(path: Path):
    """The ONNX model at ``path``; ConfigError when it cannot be read as one."""
    import onnx

    try:
        return onnx.load(str(path))
    except Exception as e:
        raise ConfigError(f"{path}: cannot be read as an ONNX file ({type(e).__name__})") from None


def network_from_onnx(path: str | Path) -> tuple[KeypointNet, dict[str, Any]]:
    """The first stage of an ONNX file from :func:`export_onnx` back in PyTorch, and its ``meta``
    (:func:`weights_from_onnx`). ConfigError when the file is not a detector's or its layers do not match its
    model config."""
    path = Path(path)
    model = _read_onnx(path)
    full = json.loads(_meta_entry(model, path).value)
    net = KeypointNet(ModelConfig.model_validate(full["model_config"])).eval()
    _fill(net, model, path)
    meta = {k: v for k, v in full.items() if k not in ("format", "format_version", "model_config")}
    return net, meta


def weights_from_onnx(net: nn.Module, path: str | Path) -> nn.Module:
    """``net`` (any of the detector's networks, built from the settings the file was trained with) given the
    weights of the ONNX file at ``path``, so that training can go on from a shipped model. The export folds
    each batch norm into the convolution before it: each such convolution gets the folded kernel, its batch
    norm the folded bias with unit scale, mean 0 and variance 1 - eps, so train it with its batch norms
    frozen, as the adapt epochs do. ConfigError when the file's layers do not match the network's."""
    path = Path(path)
    _fill(net, _read_onnx(path), path)
    return net.eval()


def _fill(net: nn.Module, model, path: Path) -> None:
    """Copy the weights of the loaded ONNX ``model`` (from ``path``) into ``net``'s layers."""
    from onnx import numpy_helper

    weights = {i.name: torch.from_numpy(numpy_helper.to_array(i).copy()) for i in model.graph.initializer}
    nodes = {op: [n for n in model.graph.node if n.op_type == op] for op in ("Conv", "Gemm")}
    convs = [m for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    linears = [m for m in net.modules() if isinstance(m, torch.nn.Linear)]
    norm_after = {  # each convolution's batch norm, where one follows it
        id(a): b
        for seq in net.modules()
        if isinstance(seq, torch.nn.Sequential)
        for a, b in zip(list(seq.children()), list(seq.children())[1:], strict=False)
        if isinstance(a, torch.nn.Conv2d) and isinstance(b, torch.nn.BatchNorm2d)
    }
    accepted = "accepted: a file exported by `rebar train` from a network of these settings"
    if len(nodes["Conv"]) != len(convs) or len(nodes["Gemm"]) != len(linears):
        raise ConfigError(
            f"{path}: holds {len(nodes['Conv'])} convolutions and {len(nodes['Gemm'])} linear layers where "
            f"its settings give {len(convs)} and {len(linears)}; {accepted}"
        )
    with torch.no_grad():
        # the export traces the layers in the order the modules were made (the linear layers matched apart)
        for node, layer in [
            *zip(nodes["Conv"], convs, strict=True),
            *zip(nodes["Gemm"], linears, strict=True),
        ]:
            w = weights[node.input[1]]
            b = weights[node.input[2]] if len(node.input) > 2 else torch.zeros(w.shape[0])
            if w.shape != layer.weight.shape:
                raise ConfigError(
                    f"{path}: a layer of shape {tuple(w.shape)} where its settings give "
                    f"{tuple(layer.weight.shape)}; {accepted}"
                )
            layer.weight.copy_(w)
            norm = norm_after.get(id(layer))
            if norm is None:
                layer.bias.copy_(b)
            else:
                norm.weight.fill_(1.0)
                norm.bias.copy_(b)
                norm.running_mean.zero_()
                norm.running_var.fill_(1.0 - norm.eps)


def quantize_onnx(src: Path, dst: Path, calibration: np.ndarray) -> Path:
    """The second stage's float file ``src`` as int8 at ``dst``: ONNX Runtime's static quantization, int8
    weights per output channel and uint8 activations ranged on the ``calibration`` patches."""
    import tempfile

    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Batches(CalibrationDataReader):
        def __init__(self) -> None:
            self._it = iter(np.array_split(calibration, max(1, len(calibration) // 64)))

        def get_next(self) -> dict[str, np.ndarray] | None:
            b = next(self._it, None)
            return None if b is None else {"patches": np.ascontiguousarray(b)}

    root_logger = logging.getLogger()
    level = root_logger.level
    # ONNX Runtime warns on the root logger that the uint8 input is not quantized (it is already 8-bit)
    root_logger.setLevel(logging.ERROR)
    try:  # in a folder beside dst, so the finished file is renamed into place atomically
        with tempfile.TemporaryDirectory(prefix=".rebar-quant-", dir=dst.parent) as tmp:
            pre, out = Path(tmp) / "pre.onnx", Path(tmp) / "int8.onnx"
            # ONNX's own shape inference: the symbolic one cannot resolve the batch axis and leaves a file
            quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
            quantize_static(
                str(pre),
                str(out),
                Batches(),
                quant_format=QuantFormat.QOperator,
                per_channel=True,
                activation_type=QuantType.QUInt8,
                weight_type=QuantType.QInt8,
                calibrate_method=CalibrationMethod.MinMax,
            )
            out.replace(dst)
    finally:
        root_logger.setLevel(level)
    return dst
