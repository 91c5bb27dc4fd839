"""A detector's model files and what runs them.

``<stem>.onnx`` is the first stage; its metadata (JSON under :data:`META_KEY`) names the later stages, each in
``<stem>.<stage>.onnx`` beside it with its SHA-256. ``runtime`` "onnxruntime" runs them in float32, "openvino"
in bfloat16 where the CPU has it, "auto" picks OpenVINO where that holds; int8 files run in ONNX Runtime."""

from __future__ import annotations

import threading
from collections.abc import Callable
from functools import cache
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Literal, get_args

import numpy as np

from rebar_data.digest import sha256_file
from rebar_data.errors import ConfigError
from rebar_data.perception.inference.checks import DepthCheck
from rebar_data.perception.inference.refine import CrossingPoint, Refiner

Runtime = Literal["auto", "onnxruntime", "openvino"]
RUNTIMES: tuple[str, ...] = get_args(Runtime)
SHAPES_KEPT = 4  # image shapes OpenVINO compiles the first stage for; one compile with them free serves more
BATCH_STEP = 8  # a batch of patches is padded to a multiple of this (a new batch size costs OpenVINO a plan)
FORMAT = "rebar-keypoint"
FORMAT_VERSION = 2
# each older format version: the last rebar-data release that reads it
READ_BY = {1: "0.1.0"}
META_KEY = "rebar_keypoint"


def check_format(meta: dict[str, Any], path: Path) -> dict[str, Any]:
    """``meta`` once it is of this code's format version; a ConfigError naming the release that reads an older
    one (format 2 holds one score bias, each check's settings in full, no retired training settings)."""
    version = meta.get("format_version")
    if version == FORMAT_VERSION:
        return meta
    if version in READ_BY:
        raise ConfigError(
            f"{path}: a model file of format {version}, which rebar-data {READ_BY[version]} reads; accepted: "
            f"format {FORMAT_VERSION} (train it again, or read it with rebar-data {READ_BY[version]})"
        )
    raise ConfigError(f"{path}: format_version {version!r} is not one this code reads ({FORMAT_VERSION})")


def onnx_session(path: Path, threads: int, runtime: str = "onnxruntime"):
    """A low-latency CPU session for a model file: ONNX Runtime's, or an :class:`OpenVinoSession` answering
    the same calls; a file OpenVINO does not read (int8) runs in ONNX Runtime."""
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
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")  # threads sleep between runs
    try:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    except Exception as e:
        raise ConfigError(f"{path}: cannot be loaded as an ONNX model ({type(e).__name__})") from None


def resolve_runtime(runtime: str) -> str:
    """ "onnxruntime" or "openvino": what ``runtime`` means on this machine."""
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


@cache
def _openvino_core() -> Any:
    try:
        import openvino

        return openvino.Core()
    except (ImportError, OSError, RuntimeError):  # not installed, or its libraries do not load here
        return None


class OpenVinoSession:
    """An ONNX file compiled by OpenVINO for the CPU, answering the calls made of an ONNX Runtime session. A
    file with free image dimensions is compiled per input shape (the first :data:`SHAPES_KEPT`, then once
    with them free); one free in the batch alone compiled once, fed batches padded to :data:`BATCH_STEP`."""

    def __init__(self, path: Path, threads: int):
        import onnx

        try:
            self._model = _openvino_core().read_model(str(path))
            proto = onnx.load(str(path), load_external_data=False)
        except Exception as e:
            raise ConfigError(f"{path}: cannot be loaded as an ONNX model ({type(e).__name__})") from None
        self._meta = SimpleNamespace(custom_metadata_map={p.key: p.value for p in proto.metadata_props})
        self._inputs, self._outputs = _args(proto.graph.input), _args(proto.graph.output)
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

    def get_inputs(self) -> list[SimpleNamespace]:
        return self._inputs

    def get_outputs(self) -> list[SimpleNamespace]:
        return self._outputs

    def get_modelmeta(self) -> SimpleNamespace:
        return self._meta

    def run(self, output_names: None, feed: dict[str, np.ndarray]) -> list[np.ndarray]:
        """Every output for ``feed`` (``output_names`` must be None: all of them, in the file's order)."""
        with self._lock:
            key = tuple((k, v.shape) for k, v in feed.items()) if self._per_shape else ()
            if key not in self._compiled:
                if len(self._compiled) >= SHAPES_KEPT:
                    key = ()  # one compile with the free dimensions left free serves every other shape
                if key not in self._compiled:
                    model = self._model.clone()
                    if key:
                        model.reshape({k: list(v.shape) for k, v in feed.items()})
                    else:  # any shape, any batch: the detector reads a frame and its mirror image in one call
                        from openvino import Dimension, PartialShape

                        free = {
                            i.any_name: [Dimension(), *list(i.get_partial_shape())[1:]] for i in model.inputs
                        }
                        model.reshape({k: PartialShape(v) for k, v in free.items()})
                    self._compiled[key] = self._compile(model)
            compiled, request = self._compiled[key]
            n = len(next(iter(feed.values())))
            pad = -n % BATCH_STEP if self._padded else 0
            if pad:
                feed = {
                    k: np.concatenate([v, np.zeros((pad, *v.shape[1:]), v.dtype)]) for k, v in feed.items()
                }
            out = request.infer(feed, share_inputs=True)  # read in place: no copy of the image or patches
            return [np.array(out[o][:n] if pad else out[o]) for o in compiled.outputs]


def _args(values: Any) -> list[SimpleNamespace]:
    """ONNX graph inputs or outputs as ONNX Runtime's ``NodeArg`` names them: free dimensions are strings."""

    def shape(v: Any) -> list[int | str]:
        return [
            d.dim_value if d.HasField("dim_value") else (d.dim_param or "?")
            for d in v.type.tensor_type.shape.dim
        ]

    return [SimpleNamespace(name=v.name, shape=shape(v)) for v in values]


def refiner_path(model: Path) -> Path:
    return model.with_name(f"{model.stem}.refine{model.suffix}")


def int8_passes_path(model: Path) -> Path:
    return model.with_name(f"{model.stem}.refine.int8.onnx")


def depth_check_path(model: Path) -> Path:
    return model.with_name(f"{model.stem}.depth{model.suffix}")


def crossing_point_path(model: Path) -> Path:
    return model.with_name(f"{model.stem}.crossing{model.suffix}")


def stage_files(model: Path) -> list[Path]:
    """Every later stage's file beside a model, whichever it has."""
    return [f(model) for f in (refiner_path, int8_passes_path, depth_check_path, crossing_point_path)]


def stage_file(
    model: Path, meta: dict[str, Any], key: str, beside: Callable[[Path], Path], *, sha_key: str = "sha256"
) -> tuple[Path, dict[str, Any]] | None:
    """The file (``beside(model)``) and meta entry of the stage ``model``'s meta names under ``key`` (None:
    none); ConfigError unless the file is there with the SHA-256 under ``sha_key``."""
    entry = meta.get(key)
    if not entry:
        return None
    path = beside(model)
    if not path.exists():
        raise ConfigError(
            f"{model}: its stage {path.name} is missing beside it; accepted: the files together, "
            f"as `rebar train` writes them ({model.name} and {path.name})"
        )
    if path.suffix == ".onnx" and entry.get(sha_key) and sha256_file(path) != entry[sha_key]:
        raise ConfigError(
            f"{path}: is not the stage {model.name} was exported with (its SHA-256 differs); "
            "accepted: the files from the same `rebar train` run"
        )
    return path, entry


def refiner_passes(entry: dict[str, Any]) -> dict[str, Any]:
    """How the second stage's passes run, as its meta entry says."""
    return {
        "iterations": int(entry["iterations"]),
        "views": int(entry["views"]),
        "first_pass_views": int(entry["first_pass_views"]),
        "step": float(entry["step"]),
        "shrink_above_px": entry.get("shrink_above_px"),
    }


def depth_check_settings(entry: dict[str, Any]) -> dict[str, float]:
    """How the depth check reads a patch and vetoes a score, as its meta entry says."""
    veto = {"power": entry["veto_power"], "margin": entry["veto_margin"]}
    return {k: float(v) for k, v in {"scale_m": entry["scale_m"], "clip": entry["clip"], **veto}.items()}


def stage_entries(model: Path, meta: dict[str, Any]) -> dict[str, tuple[Path, dict[str, Any]]]:
    """The file and meta entry (:func:`stage_file`) of each later stage ``model``'s meta names, by key."""
    beside = {"refiner": refiner_path, "depth_check": depth_check_path, "crossing_point": crossing_point_path}
    return {key: found for key, f in beside.items() if (found := stage_file(model, meta, key, f))}


def load_stages(
    model: Path, meta: dict[str, Any], threads: int, runtime: str
) -> tuple[Refiner | None, DepthCheck | None, CrossingPoint | None]:
    """The second stage (with its int8 copy where it has one), the depth check and the crossing-point stage
    ``model``'s meta names; None for each it does not."""
    refiner = depth = crossing = None
    found = stage_entries(model, meta)
    if f := found.get("refiner"):
        int8 = None
        if f[1].get("quantize") == "later":
            int8, _ = stage_file(model, meta, "refiner", int8_passes_path, sha_key="int8_sha256")
        refiner = read_refiner(f[0], threads=threads, runtime=runtime, int8_path=int8, **refiner_passes(f[1]))
    if f := found.get("depth_check"):
        depth = read_depth_check(f[0], threads=threads, runtime=runtime, **depth_check_settings(f[1]))
    if f := found.get("crossing_point"):
        crossing = read_crossing_point(f[0], threads=threads, runtime=runtime)
    return refiner, depth, crossing


def session_run(sess: Any) -> Callable[..., np.ndarray]:
    """A call of a session: its inputs in order (any given beyond them left out), its first output back."""
    names = [i.name for i in sess.get_inputs()]
    return lambda *inputs: sess.run(None, dict(zip(names, inputs, strict=False)))[0]


def read_refiner(
    path: Path, *, threads: int, int8_path: Path | None = None, runtime: str = "onnxruntime", **passes: Any
) -> Refiner:
    """The second stage in an ONNX file, its ``passes`` as :class:`Refiner` takes them (one iteration by
    default); ``int8_path``: an int8 copy for the later passes (ONNX Runtime)."""
    sess = onnx_session(path, threads, runtime)
    int8_run = None if int8_path is None else session_run(onnx_session(int8_path, threads, "onnxruntime"))
    columns = sess.get_outputs()[0].shape[-1]  # offsets, then the verification logit, then the log box side
    run, size, passes = session_run(sess), sess.get_inputs()[0].shape[1], {"iterations": 1, **passes}
    return Refiner(run, patch_px=size, verifies=columns >= 3, sizes=columns == 4, int8_run=int8_run, **passes)


def read_crossing_point(path: Path, *, threads: int, runtime: str = "onnxruntime") -> CrossingPoint:
    sess = onnx_session(path, threads, runtime)
    return CrossingPoint(session_run(sess), patch_px=sess.get_inputs()[0].shape[1])


def read_depth_check(
    path: Path, *, threads: int, runtime: str = "onnxruntime", **settings: float
) -> DepthCheck:
    """The depth check in ``path``; ``settings``: :class:`DepthCheck`'s scale_m, clip, power and margin."""
    sess = onnx_session(path, threads, runtime)
    return DepthCheck(session_run(sess), patch_px=sess.get_inputs()[0].shape[-1], **settings)
