"""What a servo run shares across its episodes: the suite, the simulated cell, the camera and its frames,
and how each episode gets its detector."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rebar_data.camera import Intrinsics
from rebar_data.geometry.build import RebarMesh
from rebar_data.servo.alignment import CrossingTruth
from rebar_data.servo.config import SuiteConfig
from rebar_data.servo.detectors import ServoDetector
from rebar_data.servo.frames import FrameSource
from rebar_data.servo.world import ServoWorld


@dataclass(kw_only=True)
class ServoContext:
    """Everything a run shares across episodes.

    ``make_detector`` builds an episode's detector from the episode's own generator (its faults draw from
    it); ``new_sensor``, where the frame source has a camera sensor of its own (the renderer's), draws a
    new one for each episode, and is None where it has none (the ray cast).
    """

    suite: SuiteConfig
    world: ServoWorld
    rm: RebarMesh
    camera: Intrinsics
    frames: FrameSource
    make_detector: Callable[[np.random.Generator], ServoDetector]
    depth_offset_m: float
    detector_name: str
    truth: CrossingTruth  # the crossings' exact bar tangents and normals, for the rows only
    new_sensor: Callable[[np.random.Generator], None] | None = None

    def close(self) -> None:
        """Release the renderer and the simulator."""
        self.frames.close()
        self.world.close()
