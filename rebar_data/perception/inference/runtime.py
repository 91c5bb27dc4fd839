"""What runs the detector's ONNX files on a CPU: ONNX Runtime in float32, or OpenVINO in bfloat16.

``runtime`` (``Detector.load``, ``rebar detect --runtime``, the bench):

- ``"onnxruntime"``: every file in float32 (the int8 copy of the second stage in int8), the same numbers on
  every x86 CPU to rounding; training fits its stages and operating points on what this runtime gives.
- ``"openvino"``: the float files in OpenVINO with bfloat16 arithmetic where the CPU has it (AVX-512 BF16
  or AMX), float32 where it has not; the int8 copy stays in ONNX Runtime (OpenVINO does not read its
  quantized operators, and the same copy quantized in QDQ form ran no faster in OpenVINO: 0.041-0.050 ms
  a patch against ONNX Runtime's 0.041-0.045, batches of 80-120).
- ``"auto"`` (the default): OpenVINO where it is installed and the CPU has bfloat16, ONNX Runtime otherwise.

Why: on this project's 2-core AMD EPYC (AVX-512 BF16), OpenVINO in bfloat16 ran the first stage on a
640x480 frame in 3.8 ms against ONNX Runtime's 7.0 ms, and 90 second-stage patches in 5.7 against 11.5 ms;
in float32 it was slower than ONNX Runtime (11.7 ms for the first stage). bfloat16 keeps 8 bits of mantissa:
the first stage's logits moved by up to 0.10 and the second stage's outputs by up to 0.05, which moved
the detector's figures by a few detections either way (the README's runtime paragraph has them).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from rebar_data.errors import ConfigError

Runtime = Literal["auto", "onnxruntime", "openvino"]
RUNTIMES: tuple[str, ...] = get_args(Runtime)
# input shapes an OpenVINO session compiles for (the first stage is compiled per image size: with its height
# and width left free it ran 5.0 ms against 3.8 ms compiled for 640x480); sizes past these are served by one
# compile with them left free, so a folder of many sizes is not compiled again image by image
SHAPES_KEPT = 4
# a batch of patches is padded to a multiple of this many: each batch size OpenVINO has not seen before costs
# it a new plan (200 calls of 20-200 patches: 0.075 ms a patch as they came, 0.060 padded to 8, 0.068 to 16)
BATCH_STEP = 8


def onnx_session(path: Path, threads: int, runtime: str = "onnxruntime"):
    """A CPU session for one of the project's model files, set up for low latency: an ONNX Runtime
    ``InferenceSession``, or for ``runtime`` "openvino" an :class:`OpenVinoSession` that answers the same
    calls (``get_inputs``, ``get_outputs``, ``get_modelmeta``, ``run``). "auto" is resolved here. A file
    OpenVINO does not read (an int8 one, in ONNX Runtime's quantized operators) runs in ONNX Runtime."""
    if resolve_runtime(runtime) == "openvino":
        try:
            return OpenVinoSession(path, threads)
        except ConfigError:
            pass  # ONNX Runtime reads it, or says why it cannot
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.log_severity_level = 3
    # threads sleep rather than spin between runs: on a 2-core machine shared with the simulator,
    # spinning doubled the latency under load and cost nothing to drop when idle
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    except Exception as e:
        raise ConfigError(f"{path}: cannot be loaded as an ONNX model ({type(e).__name__})") from None


def resolve_runtime(runtime: str) -> str:
    """ "onnxruntime" or "openvino": what ``runtime`` means on this machine (see the module's text)."""
    if runtime not in RUNTIMES:
        raise ConfigError(f"runtime {runtime!r} is not accepted; accepted: {', '.join(RUNTIMES)}")
    if runtime == "auto":
        return "openvino" if openvino_bf16() else "onnxruntime"
    if runtime == "openvino" and _openvino_core() is None:
        raise ConfigError(
            "runtime 'openvino' needs the openvino package; accepted: pip install openvino, "
            "or runtime 'onnxruntime'"
        )
    return runtime


def openvino_bf16() -> bool:
    """Whether OpenVINO is installed and runs bfloat16 on this CPU."""
    core = _openvino_core()
    return core is not None and "BF16" in core.get_property("CPU", "OPTIMIZATION_CAPABILITIES")


def runtime_description(runtime: str) -> str:
    """How ``runtime`` runs here, in words (for the bench and `rebar detect`)."""
    if resolve_runtime(runtime) == "onnxruntime":
        return "ONNX Runtime, float32"
    return f"OpenVINO, {'bfloat16' if openvino_bf16() else 'float32'}"


@cache
def _openvino_core() -> Any:
    try:
        import openvino

        return openvino.Core()
    except (ImportError, OSError, RuntimeError):  # not installed, or its libraries do not load here
        return None


@dataclass(frozen=True)
class _Arg:
    """An input or output as ONNX Runtime's ``NodeArg`` names it: free dimensions are strings."""

    name: str
    shape: list[int | str]


@dataclass(frozen=True)
class _Meta:
    custom_metadata_map: dict[str, str]


class OpenVinoSession:
    """An ONNX file compiled by OpenVINO for the CPU (bfloat16 where the CPU has it), answering the calls
    the project makes of an ONNX Runtime session. A file whose inputs have free dimensions past the first
    (the first stage's image) is compiled for each of the first :data:`SHAPES_KEPT` input shapes it is
    given (the batch of two the detector's mirrored reading gives is a shape of its own), and once more with
    them and the batch free for any other; one free only in the first (a batch of patches) is compiled once
    and given batches padded to a multiple of :data:`BATCH_STEP`; one with none free is compiled once."""

    def __init__(self, path: Path, threads: int):
        import onnx

        core = _openvino_core()
        try:
            self._model = core.read_model(str(path))
            proto = onnx.load(str(path), load_external_data=False)
        except Exception as e:
            raise ConfigError(f"{path}: cannot be loaded as an ONNX model ({type(e).__name__})") from None
        self._meta = _Meta({p.key: p.value for p in proto.metadata_props})
        self._inputs = [_arg(v) for v in proto.graph.input]
        self._outputs = [_arg(v) for v in proto.graph.output]
        self._config = {
            "INFERENCE_NUM_THREADS": threads,
            "PERFORMANCE_HINT": "LATENCY",
            "NUM_STREAMS": 1,
            "INFERENCE_PRECISION_HINT": "bf16" if openvino_bf16() else "f32",
        }
        self._per_shape = any(isinstance(d, str) for a in self._inputs for d in a.shape[1:])
        self._padded = not self._per_shape and all(
            a.shape and isinstance(a.shape[0], str) for a in self._inputs
        )
        self._compiled: dict[tuple, Any] = {}
        # an infer request serves one call at a time; ONNX Runtime's sessions may be called from threads
        self._lock = threading.Lock()
        if not self._per_shape:
            self._compiled[()] = self._compile(self._model)

    def _compile(self, model: Any) -> tuple[Any, Any]:
        compiled = _openvino_core().compile_model(model, "CPU", self._config)
        return compiled, compiled.create_infer_request()

    def get_inputs(self) -> list[_Arg]:
        return self._inputs

    def get_outputs(self) -> list[_Arg]:
        return self._outputs

    def get_modelmeta(self) -> _Meta:
        return self._meta

    def run(self, output_names: None, feed: dict[str, np.ndarray]) -> list[np.ndarray]:
        """Every output for ``feed`` (``output_names`` must be None: all of them, in the file's order)."""
        with self._lock:
            return self._run(feed)

    def _run(self, feed: dict[str, np.ndarray]) -> list[np.ndarray]:
        key = tuple((k, v.shape) for k, v in feed.items()) if self._per_shape else ()
        if key not in self._compiled:
            if len(self._compiled) >= SHAPES_KEPT:
                key = ()  # one compile with the free dimensions left free serves every other shape
            if key not in self._compiled:
                model = self._model.clone()
                if key:
                    model.reshape({k: list(v.shape) for k, v in feed.items()})
                else:  # any shape, any batch: the detector reads a frame and its mirror image in one call
                    model.reshape({i.any_name: _batch_free(i.get_partial_shape()) for i in model.inputs})
                self._compiled[key] = self._compile(model)
        compiled, request = self._compiled[key]
        n = pad = 0
        if self._padded:
            n = len(next(iter(feed.values())))
            pad = -n % BATCH_STEP
        if pad:
            feed = {k: np.concatenate([v, np.zeros((pad, *v.shape[1:]), v.dtype)]) for k, v in feed.items()}
        out = request.infer(feed, share_inputs=True)  # read in place: no copy of the image or patches
        return [np.array(out[o][:n] if pad else out[o]) for o in compiled.outputs]


def _batch_free(shape: Any) -> Any:
    """An OpenVINO input shape with its first dimension (the batch) left free."""
    import openvino

    return openvino.PartialShape([openvino.Dimension(), *list(shape)[1:]])


def _arg(value: Any) -> _Arg:
    dims = value.type.tensor_type.shape.dim
    return _Arg(value.name, [d.dim_value if d.HasField("dim_value") else (d.dim_param or "?") for d in dims])
