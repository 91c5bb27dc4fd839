"""A detector's model file and the stage files beside it: where each lives, what its metadata says, and
loading each stage the metadata names.

``<stem>.onnx`` is the first stage; its metadata (under :data:`META_KEY`, JSON) names the later stages,
each in ``<stem>.<stage>.onnx`` beside it with the SHA-256 it was written with.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rebar_data.errors import ConfigError
from rebar_data.perception.inference.crossing_point import CrossingPoint
from rebar_data.perception.inference.depth_check import DepthCheck
from rebar_data.perception.inference.refine import Refiner

FORMAT = "rebar-keypoint"
FORMAT_VERSION = 1
META_KEY = "rebar_keypoint"


def sha256_file(path: Path) -> str:
    """The hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def depth_check_path(model: Path) -> Path:
    """Where a model file's third stage lives: beside it, ``<stem>.depth.onnx`` (or ``.depth.pt``)."""
    return model.with_name(f"{model.stem}.depth{model.suffix}")


def load_depth_check(model: Path, meta: dict[str, Any], threads: int, runtime: str) -> DepthCheck | None:
    """The third stage a model file names in its meta (None when it names none)."""
    found = stage_file(model, meta, "depth_check", depth_check_path)
    if found is None:
        return None
    path, entry = found
    return DepthCheck.load_onnx(
        path, threads=threads, scale_m=float(entry["scale_m"]), clip=float(entry["clip"]), runtime=runtime
    )


def stage_file(
    model: Path,
    meta: dict[str, Any],
    key: str,
    beside: Callable[[Path], Path],
    *,
    sha_key: str = "sha256",
) -> tuple[Path, dict[str, Any]] | None:
    """The later stage that ``model``'s meta names under ``key``: its file (``beside(model)``) and its meta
    entry; None when the meta names none. ConfigError unless the file is beside the model, and is the
    file it was exported with (the entry's ``sha_key``)."""
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


def crossing_point_path(model: Path) -> Path:
    """Where a model file's crossing-point stage lives: beside it, ``<stem>.crossing.onnx`` (or ``.pt``)."""
    return model.with_name(f"{model.stem}.crossing{model.suffix}")


def load_crossing_point(
    model: Path, meta: dict[str, Any], threads: int, runtime: str
) -> CrossingPoint | None:
    """The crossing-point stage a model file names in its meta (None when it names none)."""
    found = stage_file(model, meta, "crossing_point", crossing_point_path)
    if found is None:
        return None
    return CrossingPoint.load_onnx(found[0], threads=threads, runtime=runtime)


def refiner_path(model: Path) -> Path:
    """Where a model file's second stage lives: beside it, ``<stem>.refine.onnx`` (or ``.refine.pt``)."""
    return model.with_name(f"{model.stem}.refine{model.suffix}")


def int8_passes_path(model: Path) -> Path:
    """Where the int8 copy of a model file's second stage that its passes after the first read lives
    (``RefineConfig.quantize = "later"``): beside it, ``<stem>.refine.int8.onnx``."""
    return model.with_name(f"{model.stem}.refine.int8.onnx")


def stage_files(model: Path) -> list[Path]:
    """Where a model file's later stages live beside it, whichever it has: what shipping or adapting the
    model copies with it."""
    return [f(model) for f in (refiner_path, int8_passes_path, depth_check_path, crossing_point_path)]


def load_refiner(model: Path, meta: dict[str, Any], threads: int, runtime: str) -> Refiner | None:
    """The refiner a model file names in its meta (None when it names none)."""
    found = stage_file(model, meta, "refiner", refiner_path)
    if found is None:
        return None
    path, entry = found
    int8 = None  # the int8 copy its later passes read (quantize: later)
    if entry.get("quantize") == "later":
        int8, _ = stage_file(model, meta, "refiner", int8_passes_path, sha_key="int8_sha256")
    return Refiner.load_onnx(
        path,
        threads=threads,
        runtime=runtime,
        int8_path=int8,
        **refiner_passes(entry),
    )


def refiner_passes(entry: dict[str, Any]) -> dict[str, Any]:
    """How the second stage's passes run, as its meta entry says (keys written later default to how older
    files ran)."""
    views = int(entry.get("views", 1))
    return {
        "iterations": int(entry.get("iterations", 1)),
        "views": views,
        "first_pass_views": int(entry.get("first_pass_views", views)),  # every pass alike
        "step": float(entry.get("step", 1.0)),  # each pass all the way
        "shrink_above_px": entry.get("shrink_above_px"),  # None: every pass at full resolution
    }
