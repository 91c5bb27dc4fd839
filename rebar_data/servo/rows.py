"""Building one episode's rows (:mod:`rebar_data.servo.records`) from the loop's state, by keyword.

``true`` columns are read from the simulator (the target's true point and pixel, the true camera and tool
positions); the rest is what the controller saw and did.
"""

from __future__ import annotations

import numpy as np

from rebar_data.servo.context import ServoContext
from rebar_data.servo.controllers import Controller
from rebar_data.servo.faults import faults_label
from rebar_data.servo.records import StepRow, VisitRow
from rebar_data.servo.sensing import Sensed
from rebar_data.servo.tracker import TrackState

# What a visit ended with: the tracked state, its depth, the image and metric errors, the true point
# (camera frame) and the true pixel.
Last = tuple[TrackState, float, float, float, np.ndarray, np.ndarray]


class EpisodeRows:
    """The row builder of one episode (index ``episode``, its start ``start_standoff_m`` from the mesh)."""

    def __init__(self, ctx: ServoContext, controller: Controller, *, episode: int, start_standoff_m: float):
        self.ctx, self.controller = ctx, controller
        self.episode = episode
        self.start_standoff_m = start_standoff_m

    def servo_step(
        self,
        *,
        visit: int,
        iteration: int,
        state: TrackState,
        depth_m: float,
        twist: np.ndarray,
        gain: float,
        error_px: float,
        error_m: float,
        p_true: np.ndarray,
        uv_true: np.ndarray,
        sensed: Sensed,
        qdot: np.ndarray | None = None,
    ) -> StepRow:
        """A step of the servo phase: the tracked point against the desired one, and the true errors."""
        ctl, world = self.controller, self.ctx.world
        desired = ctl.desired_px
        true_err_px = float(np.linalg.norm(uv_true - desired))
        lat, err3 = self.true_errors(p_true)
        return StepRow(
            suite=self.ctx.suite.name,
            episode=self.episode,
            visit=visit,
            mode=ctl.mode,
            phase="servo",
            iteration=iteration,
            time_s=world.time_s,
            feature_u=float(state.point[0]),
            feature_v=float(state.point[1]),
            desired_u=float(desired[0]),
            desired_v=float(desired[1]),
            error_px=float(error_px),
            error_m=float(error_m),
            depth_m=float(depth_m),
            true_u=float(uv_true[0]),
            true_v=float(uv_true[1]),
            true_error_px=true_err_px,
            true_lateral_error_m=lat,
            true_error_m=err3,
            tracker=state.source,
            detections=int(len(sensed.detections)),
            dropped=bool(sensed.dropped),
            gain=float(gain),
            twist=_floats(twist),
            q=_floats(world.q),
            qdot=_floats(qdot if qdot is not None else np.zeros(6)),
            camera_position_m=_floats(world.world_from_camera()[:3, 3]),
            tcp_position_m=_floats(world.world_from_tcp()[:3, 3]),
        )

    def motion_step(
        self, *, visit: int, phase: str, iteration: int, qdot: np.ndarray, twist: np.ndarray, error_m: float
    ) -> StepRow:
        """A step of the tool move (``approach`` or ``retract``): no image columns, the move's error."""
        world = self.ctx.world
        nan = float("nan")
        return StepRow(
            suite=self.ctx.suite.name,
            episode=self.episode,
            visit=visit,
            mode=self.controller.mode,
            phase=phase,
            iteration=iteration,
            time_s=world.time_s,
            feature_u=nan,
            feature_v=nan,
            desired_u=nan,
            desired_v=nan,
            error_px=nan,
            error_m=error_m,
            depth_m=nan,
            true_u=nan,
            true_v=nan,
            true_error_px=nan,
            true_lateral_error_m=nan,
            true_error_m=nan,
            tracker="none",
            detections=0,
            dropped=False,
            gain=0.0,
            twist=_floats(twist),
            q=_floats(world.q),
            qdot=_floats(qdot),
            camera_position_m=_floats(world.world_from_camera()[:3, 3]),
            tcp_position_m=_floats(world.world_from_tcp()[:3, 3]),
        )

    def true_errors(self, p_true: np.ndarray) -> tuple[float, float]:
        """True lateral error (to the desired line of sight) and the controller-space error, metres."""
        if not np.all(np.isfinite(p_true)):
            return float("nan"), float("nan")
        want = self.controller.desired_point_camera(p_true[2])
        lateral = float(np.linalg.norm(p_true[:2] - want[:2]))
        if self.controller.drives_position:
            return lateral, float(np.linalg.norm(p_true - self.controller.desired_point_camera(0.0)))
        return lateral, lateral

    def visit(
        self,
        *,
        visit: int,
        crossing_id: int,
        reason: str,
        iterations: int,
        initial_px: float,
        initial_m: float,
        last: Last | None,
    ) -> VisitRow:
        """A visit's row with its final errors; the tool move, tracking counts, ratios and times are the
        caller's to fill in."""
        ctx, ctl = self.ctx, self.controller
        nan = float("nan")
        final_px = final_m = true_px = lat = err3 = depth_err = nan
        if last is not None:
            _, _, final_px, final_m, p_true, uv_true = last
            true_px = float(np.linalg.norm(uv_true - ctl.desired_px))
            lat, err3 = self.true_errors(p_true)
            if ctl.drives_depth:
                depth_err = float(p_true[2] - ctl.desired_point_camera(ctx.suite.ibvs.desired_depth_m)[2])
        return VisitRow(
            suite=ctx.suite.name,
            episode=self.episode,
            visit=visit,
            target_id=int(crossing_id),
            mode=ctl.mode,
            detector=ctx.detector_name,
            converged=reason == "converged",
            reason=reason,
            iterations=int(iterations),
            initial_error_px=float(initial_px),
            final_error_px=float(final_px),
            final_true_error_px=float(true_px),
            final_true_lateral_error_m=float(lat),
            initial_error_m=float(initial_m),
            final_error_m=float(final_m),
            final_true_error_m=float(err3),
            final_true_depth_error_m=float(depth_err),
            tcp_reached=False,
            tcp_error_m=nan,
            tcp_lateral_error_m=nan,
            tcp_iterations=0,
            final_tilt_error_deg=nan,
            final_jaw_error_deg=nan,
            tied=False,
            tie_time_s=nan,
            tie_tilt_error_deg=nan,
            tie_jaw_error_deg=nan,
            tie_crossing_distance_m=nan,
            lost_frames=0,
            reseeds=0,
            max_joint_speed_ratio=0.0,
            max_joint_position_ratio=0.0,
            wall_s=0.0,
            sim_s=0.0,
            start_standoff_m=float(self.start_standoff_m),
            faults=faults_label(ctx.suite),
        )


def _floats(x) -> list[float]:
    return [float(v) for v in np.asarray(x).reshape(-1)]
