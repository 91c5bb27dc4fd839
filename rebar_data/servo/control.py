"""The control loop of one target visit: servo onto the target (the tool squared to the mat as it goes),
then the tie: the tool over the crossing, in along its axis, the dwell, and back out.

Each iteration: sense (frame, detections, every pending target's tracker), the controller's twist on the
visited target, joint velocities, one control period of physics. The loop stops when the error has
settled below the controller's bar with the point known well enough (``converged``), when the error grows
past ``divergence_factor`` times its start (``diverged``), after ``max_iterations`` (``timeout``), on
contact (``collision``), or when the target stays unseen for ``max_lost_frames`` (``lost``; before that
the arm holds still).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Protocol

import numpy as np

from rebar_data.servo.alignment import AlignmentEstimate, rotation_error
from rebar_data.servo.config import SafetyConfig
from rebar_data.servo.context import ServoContext
from rebar_data.servo.controllers import Controller
from rebar_data.servo.drawing import annotate
from rebar_data.servo.motion import orientation_hold
from rebar_data.servo.recorder import Recorder
from rebar_data.servo.records import EpisodeResult, StepRow, VisitRow
from rebar_data.servo.rows import EpisodeRows, Last
from rebar_data.servo.sensing import Sensing, Target

# Safety floors for the divergence test: an error counts as diverging only past these too.
DIVERGENCE_FLOOR_PX = 20.0
DIVERGENCE_FLOOR_M = 0.02


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
    al = cfg.align
    aligner = AlignmentEstimate(ctx.camera, al, depth_offset_m=ctx.depth_offset_m) if al.enabled else None
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
        omega, aligned = None, aligner is None
        if aligner is not None:
            R_desired = aligner.update(s.frame.depth_m, state.point, Z, ctl.camera_pose())
            if R_desired is not None:
                tu, tilt, jaw = rotation_error(R_desired)
                omega = al.gain * tu
                aligned = tilt < al.converge_tilt_deg and jaw < al.converge_jaw_deg
            was_on_lines = aligner.on_lines
            point = aligner.servo_point(state.point, ctl.camera_pose())
            if aligner.on_lines:
                if not was_on_lines:
                    ep.rec.event(ep.step_index, f"visit {k}: servoing on the bars' lines' meeting point")
                state = dataclasses.replace(state, point=point)
                # the depth where the visit servos: the detection's pixel may lie off the bar (a mat's edge)
                z = ep.sensing.crossing_depth(s.frame, point)
                Z = z if np.isfinite(z) else Z
        twist, err_px, err_m = ctl.twist(state.point, Z, omega)
        if not np.isfinite(initial_px):
            initial_px, initial_m = err_px, err_m
        last = (state, Z, err_px, err_m, p_true, uv_true)
        ep.rec.frame(ep.step_index, s.frame, s.detections, track=state, desired=ctl.desired_px)
        known = state.sigma_px <= cfg.safety.converge_sigma_px
        settle = settle + 1 if ctl.converged(err_px, err_m) and known and aligned else 0
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
        qdot = world.command(ctl.joint_rates(twist, hold=False if omega is not None else None))
        _keep_servo_step(ep, ep.rows.servo_step(twist=twist, gain=ctl.last_gain, qdot=qdot, **step))
        ep.rec.state(ep.step_index, world)
        world.step()
        ep.step_index += 1
        speed_ratio = max(speed_ratio, float(np.max(np.abs(world.qdot) / world.limits.speed)))
        if world.in_contact():
            reason = "collision"
            break
    world.command(np.zeros(6))
    if reason == "converged" and aligner is not None and not aligner.with_bars:
        # a crossing is two bars on the front mat: a target where no frame resolved them (a top bar over a
        # lower one, a spurious detection) is not tied
        reason = "no_crossing"

    row = ep.rows.visit(
        visit=k,
        crossing_id=target.crossing_id,
        reason=reason,
        iterations=iterations,
        initial_px=initial_px,
        initial_m=initial_m,
        last=last,
    )
    row.final_tilt_error_deg, row.final_jaw_error_deg = ctx.truth.errors(
        target.crossing_id, world.world_from_tcp(), al.jaw_to_bar_deg
    )
    row.feature = "bar_lines" if aligner is not None and aligner.on_lines else "detection"
    row.lost_frames = target.tracker.lost_total - lost0
    row.reseeds = target.tracker.reseeds - reseeds0
    ep.rec.event(ep.step_index, f"visit {k}: {reason} after {iterations} iterations")
    ep.rec.scalars_gap(ep.step_index)
    if row.converged and cfg.tcp.approach and last is not None:
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
    """The tie: the tool over the crossing, in along its axis to the stand-off, the dwell, back out.

    The crossing's position in the camera frame (back-projected at convergence) is put into the tool's
    frame by ``tcp_from_camera``; the arm then translates the tool, with the camera's orientation held, in
    closed loop on its own pose estimate (the kinematic model for IBVS, the measured pose for PBVS): to
    ``clearance_m`` out from the crossing along the tool's axis, along the axis to ``standoff_m``, where the
    tie is made (``dwell_s`` still), then back out along the axis and to where it started. Fills the row's
    ``tcp_`` and ``tie_`` columns; returns the largest joint speed ratio.
    """
    ctx, world, ctl = ep.ctx, ep.ctx.world, ep.controller
    cfg = ctx.suite.tcp
    state, Z = last[0], last[1]
    p_cam = ctx.camera.back_project(state.point[None], np.array([Z]))[0]
    camera_from_tcp = world.layout.camera_from_tcp
    axis = camera_from_tcp[:3, 2]  # the tool's axis, parallel to the camera's
    T_before = ctl.camera_pose()

    def camera_goal(tcp_in_camera: np.ndarray) -> np.ndarray:
        # the camera moved by the offset that puts the tool centre point at ``tcp_in_camera``
        goal = T_before.copy()
        goal[:3, 3] = T_before[:3, 3] + T_before[:3, :3] @ (tcp_in_camera - camera_from_tcp[:3, 3])
        return goal

    tie = p_cam - cfg.standoff_m * axis
    over = tie - cfg.clearance_m * axis
    move = {"max_iterations": cfg.max_iterations, "speed_m_s": cfg.speed_m_s, "gain": cfg.gain}
    it1, _, ratio = move_camera_to(
        ep, k, camera_goal(over), phase="approach", tol=cfg.waypoint_tolerance_m, **move
    )
    it2, reached, r2 = move_camera_to(ep, k, camera_goal(tie), phase="approach", tol=cfg.tolerance_m, **move)
    row.tcp_reached = bool(reached)
    row.tcp_iterations = it1 + it2
    crossing = ctx.rm.crossings.point[target.crossing_id] if target.crossing_id >= 0 else np.full(3, np.nan)
    _tool_errors(ep, row, crossing)
    if reached:
        row.tied, row.tie_time_s = True, world.time_s
        _dwell(ep, k, camera_goal(tie), row, crossing)
        tcp_true = world.world_from_tcp()
        ep.rec.tie(ep.step_index, tcp_true[:3, 3] + cfg.standoff_m * tcp_true[:3, 2], tcp_true[:3, 2], row)
    ep.rec.event(
        ep.step_index,
        f"visit {k}: {'tied' if reached else 'not tied'}, tool {row.tcp_error_m * 1000:.2f} mm, "
        f"tilt {row.tie_tilt_error_deg:.2f} deg, jaw {row.tie_jaw_error_deg:.2f} deg",
    )
    _, _, r3 = move_camera_to(ep, k, camera_goal(over), phase="retract", tol=cfg.waypoint_tolerance_m, **move)
    _, _, r4 = move_camera_to(ep, k, T_before, phase="retract", tol=cfg.waypoint_tolerance_m, **move)
    return max(ratio, r2, r3, r4)


def _tool_errors(ep: Episode, row: VisitRow, crossing: np.ndarray) -> None:
    """The tool's true errors now into the row, where worse than what it holds (the worst over the tie)."""
    ctx, world = ep.ctx, ep.ctx.world
    standoff = ctx.suite.tcp.standoff_m
    tcp_true = world.world_from_tcp()
    axis = tcp_true[:3, 2]
    err = tcp_true[:3, 3] - (crossing - standoff * axis)
    tip = tcp_true[:3, 3] + standoff * axis  # where the gun ties
    tilt, jaw = ctx.truth.errors(row.target_id, tcp_true, ctx.suite.align.jaw_to_bar_deg)
    now = {
        "tcp_error_m": float(np.linalg.norm(err)),
        "tcp_lateral_error_m": float(np.linalg.norm(err - (err @ axis) * axis)),
        "tie_crossing_distance_m": float(np.min(np.linalg.norm(ctx.rm.crossings.point - tip, axis=1))),
        "tie_tilt_error_deg": tilt,
        "tie_jaw_error_deg": jaw,
    }
    for name, value in now.items():
        held = getattr(row, name)
        if not np.isfinite(held) or value > held:
            setattr(row, name, value)


def _dwell(ep: Episode, k: int, goal: np.ndarray, row: VisitRow, crossing: np.ndarray) -> None:
    """The tie: the tool held at the camera pose ``goal`` in closed loop (as the arm's controller holds a
    pose) for ``tcp.dwell_s`` (rows of phase ``tie``); the row's tool errors are the worst over it."""
    cfg = ep.ctx.suite.tcp
    n = int(round(cfg.dwell_s / ep.ctx.world.cfg.control_period_s))
    for it in range(n):
        twist, err_m = _tool_twist(ep, goal, speed_m_s=cfg.speed_m_s, gain=cfg.gain)
        _tool_step(ep, k, "tie", it, twist, err_m, cfg.speed_m_s)
        _tool_errors(ep, row, crossing)


def move_camera_to(
    ep: Episode,
    k: int,
    goal: np.ndarray,
    *,
    phase: str,
    max_iterations: int,
    tol: float,
    speed_m_s: float,
    gain: float,
) -> tuple[int, bool, float]:
    """Move the arm so that its camera comes to ``goal``, on the controller's pose estimate, its orientation
    held; the move ends with the tool centre point within ``tol`` of where ``goal`` puts it. Returns
    (iterations, reached, the largest joint speed ratio)."""
    world = ep.ctx.world
    ep.controller.reference = goal
    ratio, first = 0.0, None
    for it in range(max_iterations):
        twist, err_m = _tool_twist(ep, goal, speed_m_s=speed_m_s, gain=gain)
        if err_m < tol:
            world.command(np.zeros(6))
            return it, True, ratio
        first = err_m if first is None else first
        if err_m > 1.5 * first + DIVERGENCE_FLOOR_M:
            break  # the arm is not getting there (a singularity on the way): stop, not tied
        _tool_step(ep, k, phase, it, twist, err_m, speed_m_s)
        ratio = max(ratio, float(np.max(np.abs(world.qdot) / world.limits.speed)))
    world.command(np.zeros(6))
    return it + 1, False, ratio


def _tool_twist(ep: Episode, goal: np.ndarray, *, speed_m_s: float, gain: float) -> tuple[np.ndarray, float]:
    """The camera twist that drives the tool centre point to where the camera pose ``goal`` puts it, with
    the camera's orientation turned to ``goal``'s (so a lag of the orientation moves the camera, not the
    tool), and the tool's distance from there (m)."""
    world, ctl, motion = ep.ctx.world, ep.controller, ep.ctx.suite.motion
    camera_from_tcp = world.layout.camera_from_tcp
    r = camera_from_tcp[:3, 3]  # the tool centre point in the camera frame
    T = ctl.camera_pose()
    e = T[:3, :3].T @ ((goal @ camera_from_tcp)[:3, 3] - (T @ camera_from_tcp)[:3, 3])
    omega = orientation_hold(T, goal, motion.orientation_gain)
    v_tcp = gain * e
    v_tcp *= min(1.0, speed_m_s / max(float(np.linalg.norm(v_tcp)), 1e-12))
    return np.concatenate([v_tcp - np.cross(omega, r), omega]), float(np.linalg.norm(e))  # v + omega x r at r


def _tool_step(
    ep: Episode, k: int, phase: str, it: int, twist: np.ndarray, err_m: float, speed_m_s: float
) -> None:
    """One control period of a tool move: the command, its row, the physics."""
    world = ep.ctx.world
    qdot = world.command(ep.controller.joint_rates(twist, hold=False, speed_m_s=2.0 * speed_m_s))
    ep.rec.state(ep.step_index, world)
    ep.result.steps.append(
        ep.rows.motion_step(visit=k, phase=phase, iteration=it, qdot=qdot, twist=twist, error_m=err_m)
    )
    ep.rec.scalars(ep.step_index, {"tool_move_error_mm": err_m * 1000})
    world.step()
    ep.step_index += 1
