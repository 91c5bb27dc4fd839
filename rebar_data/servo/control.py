"""The control loop of one target visit: servo onto the target, then move the tool onto it and back.

Each iteration: sense (frame, detections, every pending target's tracker), the controller's twist on the
visited target, joint velocities, one control period of physics. The loop stops when the error has
settled below the controller's bar with the point known well enough (``converged``), when the error grows
past ``divergence_factor`` times its start (``diverged``), after ``max_iterations`` (``timeout``), on
contact (``collision``), or when the target stays unseen for ``max_lost_frames`` (``lost``; before that
the arm holds still).
"""

from __future__ import annotations

import time
from typing import Protocol

import numpy as np

from rebar_data.servo.config import SafetyConfig
from rebar_data.servo.context import ServoContext
from rebar_data.servo.controllers import Controller
from rebar_data.servo.drawing import annotate
from rebar_data.servo.recorder import Recorder
from rebar_data.servo.records import EpisodeResult, StepRow, VisitRow
from rebar_data.servo.rows import EpisodeRows, Last
from rebar_data.servo.sensing import Sensing, Target

# Safety floors for the divergence test: an error counts as diverging only past these too.
DIVERGENCE_FLOOR_PX = 20.0
DIVERGENCE_FLOOR_M = 0.02
TOOL_MOVE_GAIN = 6.0


class Episode(Protocol):
    """What a visit uses of its episode (:class:`rebar_data.servo.episode.EpisodeRunner`)."""

    ctx: ServoContext
    controller: Controller
    sensing: Sensing
    rows: EpisodeRows
    rec: Recorder
    result: EpisodeResult
    pending: list[Target]
    step_index: int
    keep_snapshots: bool

    def hold(self) -> None:
        """Command the arm still for one control period."""
        ...


def visit(ep: Episode, k: int, target: Target) -> None:
    """Visit the k-th target: servo, then (converged, with ``tcp.approach``) the tool move; one visit row."""
    ctx, world, ctl = ep.ctx, ep.ctx.world, ep.controller
    cfg = ctx.suite
    t0_wall, t0_sim = time.perf_counter(), world.time_s
    lost0, reseeds0 = target.tracker.lost_total, target.tracker.reseeds
    ctl.begin()
    ep.rec.event(
        ep.step_index,
        f"visit {k}: target at ({target.tracker.point[0]:.1f}, {target.tracker.point[1]:.1f}) px",
    )
    if target.crossing_id >= 0:
        ep.rec.target(
            ep.step_index,
            ctx.rm.crossings.point[target.crossing_id],
            f"T{k + 1}: crossing {target.crossing_id}",
        )

    reason, iterations, settle = "timeout", 0, 0
    initial_px = initial_m = float("nan")
    last: Last | None = None
    speed_ratio = 0.0
    for it in range(cfg.safety.max_iterations + 1):
        s = ep.sensing.sense(ep.pending)
        state = target.state
        p_true, uv_true = ep.sensing.truth(target.crossing_id)
        iterations = it
        blind = target.tracker.frames_since_detection
        if state.lost or blind > cfg.safety.max_blind_frames:
            # Not seen for too long: hold still and look again; give up after max_lost_frames.
            _keep_servo_step(
                ep,
                ep.rows.servo_step(
                    visit=k,
                    iteration=it,
                    state=state,
                    depth_m=float("nan"),
                    twist=np.zeros(6),
                    gain=0.0,
                    error_px=np.nan,
                    error_m=np.nan,
                    p_true=p_true,
                    uv_true=uv_true,
                    sensed=s,
                ),
            )
            ep.rec.frame(ep.step_index, s.frame, s.detections, track=state, desired=ctl.desired_px)
            if max(blind, target.tracker.lost_frames) > cfg.safety.max_lost_frames:
                reason = "lost"
                break
            ep.hold()
            settle = 0
            continue
        Z = target.depth_m
        twist, err_px, err_m = ctl.twist(state.point, Z)
        if not np.isfinite(initial_px):
            initial_px, initial_m = err_px, err_m
        last = (state, Z, err_px, err_m, p_true, uv_true)
        ep.rec.frame(ep.step_index, s.frame, s.detections, track=state, desired=ctl.desired_px)
        known = state.sigma_px <= cfg.safety.converge_sigma_px
        settle = settle + 1 if ctl.converged(err_px, err_m) and known else 0
        stop = _stop_reason(
            cfg.safety,
            ctl,
            settle=settle,
            iteration=it,
            error_px=err_px,
            error_m=err_m,
            initial_px=initial_px,
            initial_m=initial_m,
        )
        step = {
            "visit": k,
            "iteration": it,
            "state": state,
            "depth_m": Z,
            "error_px": err_px,
            "error_m": err_m,
            "p_true": p_true,
            "uv_true": uv_true,
            "sensed": s,
        }
        if stop is not None:
            _keep_servo_step(ep, ep.rows.servo_step(twist=np.zeros(6), gain=ctl.last_gain, **step))
            reason = stop
            if stop == "converged" and ep.keep_snapshots:
                img = annotate(
                    s.frame.rgb, detections=s.detections, track=state.point, desired=ctl.desired_px
                )
                ep.result.snapshots.append((f"T{k + 1} converged, {it} iterations", img))
            break
        qdot = world.command(ctl.joint_rates(twist))
        _keep_servo_step(ep, ep.rows.servo_step(twist=twist, gain=ctl.last_gain, qdot=qdot, **step))
        ep.rec.state(ep.step_index, world)
        world.step()
        ep.step_index += 1
        speed_ratio = max(speed_ratio, float(np.max(np.abs(world.qdot) / world.limits.speed)))
        if world.in_contact():
            reason = "collision"
            break
    world.command(np.zeros(6))

    row = ep.rows.visit(
        visit=k,
        crossing_id=target.crossing_id,
        reason=reason,
        iterations=iterations,
        initial_px=initial_px,
        initial_m=initial_m,
        last=last,
    )
    row.lost_frames = target.tracker.lost_total - lost0
    row.reseeds = target.tracker.reseeds - reseeds0
    ep.rec.event(ep.step_index, f"visit {k}: {reason} after {iterations} iterations")
    ep.rec.scalars_gap(ep.step_index)
    if reason == "converged" and cfg.tcp.approach and last is not None:
        speed_ratio = max(speed_ratio, tool_move(ep, k, target, last, row))
    row.max_joint_speed_ratio = speed_ratio
    row.max_joint_position_ratio = _position_ratio(ep, k)
    row.wall_s = time.perf_counter() - t0_wall
    row.sim_s = world.time_s - t0_sim
    ep.result.visits.append(row)


def _stop_reason(
    safety: SafetyConfig,
    ctl: Controller,
    *,
    settle: int,
    iteration: int,
    error_px: float,
    error_m: float,
    initial_px: float,
    initial_m: float,
) -> str | None:
    """Why the servo phase ends after this step (``converged``, ``diverged``, ``timeout``), or None."""
    if settle >= safety.settle_frames:
        return "converged"
    if error_px > safety.divergence_factor * max(initial_px, DIVERGENCE_FLOOR_PX) or (
        ctl.drives_position and error_m > safety.divergence_factor * max(initial_m, DIVERGENCE_FLOOR_M)
    ):
        return "diverged"
    if iteration == safety.max_iterations:
        return "timeout"
    return None


def _keep_servo_step(ep: Episode, row: StepRow) -> None:
    """Keep a servo step's row and record its errors."""
    ep.result.steps.append(row)
    ep.rec.scalars(
        ep.step_index,
        {
            "error_px": row.error_px,
            "true_error_px": row.true_error_px,
            "error_mm": row.error_m * 1000,
            "true_lateral_error_mm": row.true_lateral_error_m * 1000,
            "gain": row.gain,
        },
    )


def _position_ratio(ep: Episode, k: int) -> float:
    """The largest |q| / limit over the visit's recorded steps (and now)."""
    world = ep.ctx.world
    qs = [np.abs(r.q) for r in ep.result.steps if r.visit == k]
    qs.append(np.abs(world.q))
    return float(np.max(np.max(qs, axis=0) / world.limits.upper))


def tool_move(ep: Episode, k: int, target: Target, last: Last, row: VisitRow) -> float:
    """Move the tool centre point onto the crossing with the hand-eye transform, measure, come back.

    The crossing's position in the camera frame (back-projected at convergence) is put into the
    tool's frame by ``tcp_from_camera``; the arm then translates the tool there in closed loop on its
    own pose estimate (the kinematic model for IBVS, the measured pose for PBVS), with the camera's
    orientation held, and returns to where it was. Fills the row's ``tcp_`` columns; returns the largest
    joint speed ratio.
    """
    ctx, world, ctl = ep.ctx, ep.ctx.world, ep.controller
    cfg = ctx.suite.tcp
    state, Z = last[0], last[1]
    p_cam = ctx.camera.back_project(state.point[None], np.array([Z]))[0]
    camera_from_tcp = world.layout.camera_from_tcp
    # Camera and tool axes are parallel: putting the tool on the crossing moves the camera by the
    # crossing's offset from the tool point, less the standoff along the tool axis.
    delta = p_cam - camera_from_tcp[:3, 3] - cfg.standoff_m * camera_from_tcp[:3, 2]
    T_before = ctl.camera_pose()
    goal = T_before.copy()
    goal[:3, 3] = T_before[:3, 3] + T_before[:3, :3] @ delta
    iterations, reached, ratio = _move_camera_to(
        ep, k, goal, phase="approach", max_iterations=cfg.max_iterations, tol=cfg.tolerance_m
    )
    tcp_true = world.world_from_tcp()
    crossing = ctx.rm.crossings.point[target.crossing_id] if target.crossing_id >= 0 else np.full(3, np.nan)
    axis = tcp_true[:3, 2]
    err = tcp_true[:3, 3] - (crossing - cfg.standoff_m * axis)
    row.tcp_reached = bool(reached)
    row.tcp_error_m = float(np.linalg.norm(err))
    row.tcp_lateral_error_m = float(np.linalg.norm(err - (err @ axis) * axis))
    row.tcp_iterations = iterations
    ep.rec.event(
        ep.step_index, f"visit {k}: tool on the crossing, true error {row.tcp_error_m * 1000:.2f} mm"
    )
    _, _, back = _move_camera_to(
        ep, k, T_before, phase="retract", max_iterations=cfg.max_iterations, tol=cfg.tolerance_m
    )
    return max(ratio, back)


def _move_camera_to(
    ep: Episode, k: int, goal: np.ndarray, *, phase: str, max_iterations: int, tol: float
) -> tuple[int, bool, float]:
    """Translate the camera to ``goal`` on the controller's pose estimate: (iterations, reached, the
    largest joint speed ratio)."""
    world, ctl = ep.ctx.world, ep.controller
    ctl.reference = goal
    ratio = 0.0
    for it in range(max_iterations):
        T = ctl.camera_pose()
        e_cam = T[:3, :3].T @ (goal[:3, 3] - T[:3, 3])
        if np.linalg.norm(e_cam) < tol:
            world.command(np.zeros(6))
            return it, True, ratio
        twist = np.zeros(6)
        twist[:3] = TOOL_MOVE_GAIN * e_cam
        qdot = world.command(ctl.joint_rates(twist))
        ep.rec.state(ep.step_index, world)
        err_m = float(np.linalg.norm(e_cam))
        ep.result.steps.append(
            ep.rows.motion_step(visit=k, phase=phase, iteration=it, qdot=qdot, twist=twist, error_m=err_m)
        )
        ep.rec.scalars(ep.step_index, {"tool_move_error_mm": err_m * 1000})
        world.step()
        ep.step_index += 1
        ratio = max(ratio, float(np.max(np.abs(world.qdot) / world.limits.speed)))
    world.command(np.zeros(6))
    return max_iterations, False, ratio
