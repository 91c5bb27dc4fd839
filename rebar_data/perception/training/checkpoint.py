"""A ``.pt`` checkpoint read into a :class:`~rebar_data.perception.inference.detector.Detector`: its first
stage and the later stages' ``.pt`` files beside it, run in eager PyTorch.

:meth:`Detector.load` reads a ``.pt`` file through :func:`read_detector_checkpoint`, which it names in
:data:`~rebar_data.perception.inference.detector.READERS` and imports only then."""

from __future__ import annotations

from pathlib import Path

from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.networks import eager
from rebar_data.perception.networks.files import load_checkpoint
from rebar_data.perception.training import crossing_point, depth_check, refine


def read_detector_checkpoint(path: Path, *, threads: int, runtime: str) -> Detector:
    """The detector in the checkpoint ``path`` with the later stages its meta names; PyTorch runs it
    whatever ``threads`` and ``runtime`` say (they choose among the ``.onnx`` runtimes)."""
    net, meta, _ = load_checkpoint(path)
    det = eager.detector(net, meta=meta, path=path)
    found = model_file.stage_entries(path, det.meta)
    if f := found.get("refiner"):
        det.refiner = eager.refiner(refine.load(f[0])[0], **model_file.refiner_passes(f[1]))
    if f := found.get("depth_check"):
        det.depth_check = eager.depth_check(
            depth_check.load(f[0])[0], **model_file.depth_check_settings(f[1])
        )
    if f := found.get("crossing_point"):
        det.crossing_point = eager.crossing_point(crossing_point.load(f[0])[0])
    return det
