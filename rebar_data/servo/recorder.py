"""What the episode loop tells a recording, as calls on a :class:`Recorder`.

This base records nothing; :class:`rebar_data.servo.recording.RerunRecorder` writes the same calls to a
Rerun ``.rrd`` file. Kept apart from it so that running an episode never needs Rerun.
"""

from __future__ import annotations

import numpy as np

from rebar_data.servo.frames import CameraFrame
from rebar_data.servo.world import ServoWorld


class Recorder:
    """What the loop tells a recording; this base records nothing (see :mod:`rebar_data.servo.recording`)."""

    def frame(self, step: int, frame: CameraFrame, detections: np.ndarray, **kw) -> None: ...

    def state(self, step: int, world: ServoWorld, **kw) -> None: ...

    def scalars(self, step: int, values: dict[str, float]) -> None: ...

    def scalars_gap(self, step: int) -> None: ...

    def target(self, step: int, point_world: np.ndarray, label: str) -> None: ...

    def event(self, step: int, text: str) -> None: ...

    def tie(self, step: int, point_world: np.ndarray, axis_world: np.ndarray, row) -> None: ...

    def close(self) -> None: ...
