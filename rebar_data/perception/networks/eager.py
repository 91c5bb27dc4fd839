"""The detector's stages run from networks in memory (eager PyTorch), as training scores them before it
writes their files: each wraps a network in the run-time class that its ONNX file loads into."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from rebar_data.perception.inference.checks import DepthCheck
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.inference.refine import CrossingPoint, Refiner
from rebar_data.perception.networks.keypoint_net import KeypointNet, UInt8Input
from rebar_data.perception.networks.stages import CrossingNet, DepthNet, PatchNet


def detector(net: KeypointNet, *, meta: dict[str, Any] | None = None, path: Path | None = None) -> Detector:
    """A :class:`Detector` whose first stage is ``net``; no later stages."""
    net = net.eval()

    def run(image: np.ndarray, rays: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float()
            return net(x, torch.from_numpy(rays)[None])[0].numpy()

    return Detector(run, meta=dict(meta or {}), backend="torch", path=path)


def refiner(net: PatchNet, *, iterations: int = 1, **passes: Any) -> Refiner:
    """A second stage that runs ``net``, its passes as the arguments say (:class:`Refiner`)."""
    wrapped = UInt8Input(net.eval())  # uint8 (N, P, P, C) in, as the ONNX file takes them

    def run(x: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return wrapped(torch.from_numpy(x)).numpy()

    return Refiner(
        run, patch_px=net.patch_px, iterations=iterations, verifies=net.verify, sizes=net.size, **passes
    )


def depth_check(net: DepthNet, **settings: float) -> DepthCheck:
    """A depth check that runs ``net``; ``settings``: :class:`DepthCheck`'s scale_m, clip, power, margin."""
    net = net.eval()

    def run(x: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return net(torch.from_numpy(x)).numpy()

    return DepthCheck(run, patch_px=net.patch_px, **settings)


def crossing_point(net: CrossingNet) -> CrossingPoint:
    """A crossing-point stage that runs ``net``."""
    wrapped = UInt8Input(net.eval())

    def run(x: np.ndarray, rays: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return wrapped(torch.from_numpy(x), torch.from_numpy(rays)).numpy()

    return CrossingPoint(run, patch_px=net.patch_px)
