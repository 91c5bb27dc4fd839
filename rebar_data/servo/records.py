"""The rows the servo run writes: one per control step (``steps.parquet``), one per target visit
(``episodes.parquet``). "true" columns come from the simulator's ground truth, never from the detector.

The rows are keyword-only: a parquet file's columns are their fields, in this order, so a row is never built
from a list of values in an order that could drift from it. :mod:`rebar_data.servo.rows` builds them.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np


@dataclass(kw_only=True)
class StepRow:
    suite: str
    episode: int
    visit: int
    mode: str
    phase: str  # servo | approach | tie | retract | transfer (a tour's move to view its next target)
    iteration: int
    time_s: float
    feature_u: float
    feature_v: float
    desired_u: float
    desired_v: float
    error_px: float
    error_m: float
    depth_m: float
    true_u: float
    true_v: float
    true_error_px: float
    true_lateral_error_m: float
    true_error_m: float
    tracker: str
    detections: int
    dropped: bool
    gain: float
    twist: list[float]
    q: list[float]
    qdot: list[float]
    camera_position_m: list[float]
    tcp_position_m: list[float]


@dataclass(kw_only=True)
class VisitRow:
    suite: str
    episode: int
    visit: int
    target_id: int  # the true crossing the visit's target is (-1: no true crossing near it)
    mode: str
    detector: str
    converged: bool
    reason: str  # converged | diverged | lost | timeout | collision | no_target | no_crossing
    iterations: int
    initial_error_px: float
    final_error_px: float
    final_true_error_px: float
    final_true_lateral_error_m: float
    initial_error_m: float
    final_error_m: float
    final_true_error_m: float
    final_true_depth_error_m: float
    tcp_reached: bool
    tcp_error_m: float
    tcp_lateral_error_m: float
    tcp_iterations: int
    # the tool's true alignment with the crossing (degrees): at the servo's end, and at the tie
    final_tilt_error_deg: float
    final_jaw_error_deg: float
    tied: bool
    tie_time_s: float  # simulated time when the tie was made (the dwell's start)
    tie_tilt_error_deg: float
    tie_jaw_error_deg: float
    # the tie point's distance to the nearest crossing of the top mat: a tie on the lower mat, or between
    # crossings, lies far from every one
    tie_crossing_distance_m: float
    lost_frames: int
    reseeds: int
    max_joint_speed_ratio: float
    max_joint_position_ratio: float
    wall_s: float
    sim_s: float
    start_standoff_m: float
    faults: str = field(default="none")
    # what the visit servoed on at its end: the tracked detection, or the bars' lines' meeting point
    # (``bar_lines``: where the two disagreed, :class:`rebar_data.servo.alignment.AlignmentEstimate`)
    feature: str = field(default="detection")

    def to_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, np.floating) else v) for k, v in asdict(self).items()}


@dataclass(kw_only=True)
class EpisodeResult:
    """One episode's rows, and the annotated camera views its report shows (title, RGB image)."""

    visits: list[VisitRow] = field(default_factory=list)
    steps: list[StepRow] = field(default_factory=list)
    snapshots: list[tuple[str, np.ndarray]] = field(default_factory=list)
