"""A suite's detector faults: the wrapper that adds them to its detector, and their label in the rows."""

from __future__ import annotations

import numpy as np

from rebar_data.camera import Intrinsics
from rebar_data.servo.config import SuiteConfig
from rebar_data.servo.detectors import Faults, FaultyDetector, ServoDetector


def faults_label(suite: SuiteConfig) -> str:
    """The suite's faults in words (the ``faults`` column of ``episodes.parquet``), ``none`` without any."""
    f = suite.faults
    parts = []
    if f.drop_fraction:
        parts.append(f"drop {f.drop_fraction:.0%}")
    if f.pixel_noise_px:
        parts.append(f"noise {f.pixel_noise_px:g} px")
    if f.spurious_per_frame:
        parts.append(f"spurious {f.spurious_per_frame:g}/frame")
    return ", ".join(parts) or "none"


def faulty(
    detector: ServoDetector, suite: SuiteConfig, rng: np.random.Generator, camera: Intrinsics
) -> ServoDetector:
    """The suite's detector with its faults (or as it is when the suite has none)."""
    f = Faults(
        drop_fraction=suite.faults.drop_fraction,
        pixel_noise_px=suite.faults.pixel_noise_px,
        spurious_per_frame=suite.faults.spurious_per_frame,
    )
    if not f.active:
        return detector
    return FaultyDetector(detector, f, rng, width=camera.width, height=camera.height)
