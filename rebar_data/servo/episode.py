"""One episode: start pose, target acquisition, then each target visited in turn (servo, tool move, back).

Every control step is: frame -> detections -> every pending target's tracker -> the controller on the
current target -> joint velocities -> one control period of physics. All targets of the episode are
tracked from acquisition on, so each one has averaged its detections before its visit starts.

Safety is part of the loop: a lost target holds the arm still until it is seen again (or the visit ends
as ``lost``); an error growing past ``divergence_factor`` times its start ends the visit as
``diverged``; contact with the mesh or the table ends it as ``collision``; every command is clipped so
that no joint passes its speed or position limit.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from rebar_data.camera import Intrinsics, rigid_inverse
from rebar_data.geometry.build import RebarMesh
from rebar_data.servo.camera import KINECT_RANGE_M, depth_at
from rebar_data.servo.config import EpisodeSpec, StartPose, SuiteConfig
from rebar_data.servo.controllers import IbvsController, PbvsController
from rebar_data.servo.detectors import Detector, Faults, FaultyDetector
from rebar_data.servo.frames import Frame, FrameSource
from rebar_data.servo.records import StepRow, VisitRow
from rebar_data.servo.targets import persistent_clusters, select_targets
from rebar_data.servo.tracker import TargetTracker, TrackerConfig, TrackState
from rebar_data.servo.transforms import apply
from rebar_data.servo.world import ServoWorld

# Frame-to-frame accuracy of the arm's own motion prediction of a still point: a floor, plus the pixel
# error that a depth error of DEPTH_SIGMA_M makes of the camera's lateral motion.
MOTION_SIGMA_PX = 0.02
DEPTH_SIGMA_M = 0.002
# Safety floors for the divergence test: an error counts as diverging only past these too.
DIVERGENCE_FLOOR_PX = 20.0
DIVERGENCE_FLOOR_M = 0.02
TOOL_MOVE_GAIN = 6.0


class Recorder:
    """What the loop tells a recording; this base records nothing (see :mod:`rebar_data.servo.recording`)."""

    def frame(self, step: int, frame: Frame, detections: np.ndarray, **kw) -> None: ...

    def state(self, step: int, world: ServoWorld, **kw) -> None: ...

    def scalars(self, step: int, values: dict[str, float]) -> None: ...

    def scalars_gap(self, step: int) -> None: ...

    def target(self, step: int, point_world: np.ndarray, label: str) -> None: ...

    def event(self, step: int, text: str) -> None: ...

    def close(self) -> None: ...


@dataclass
class ServoContext:
    """Everything a run shares across episodes."""

    suite: SuiteConfig
    world: ServoWorld
    rm: RebarMesh
    camera: Intrinsics
    frames: FrameSource
    make_detector: Callable[[np.random.Generator], Detector]
    depth_offset_m: float
    detector_name: str

    def close(self) -> None:
        """Release the renderer and the simulator."""
        self.frames.close()
        self.world.close()


@dataclass
class Target:
    """A chosen target and its tracker. ``crossing_id`` is the true crossing it is (for reports only;
    -1 when no true crossing projects near it)."""

    uv: np.ndarray
    crossing_id: int
    tracker: TargetTracker
    state: TrackState | None = None
    pose: np.ndarray | None = None  # the controller's camera pose estimate at the last update
    depth_m: float = float("nan")  # the crossing's depth at the last update


@dataclass
class EpisodeResult:
    visits: list[VisitRow] = field(default_factory=list)
    steps: list[StepRow] = field(default_factory=list)
    snapshots: list[tuple[str, np.ndarray]] = field(default_factory=list)  # annotated camera views


@dataclass
class Sensed:
    frame: Frame
    detections: np.ndarray
    dropped: bool


def annotate(rgb: np.ndarray, *, detections=None, targets=None, track=None, desired=None) -> np.ndarray:
    """A copy of a camera image with detections (white), numbered targets (orange), the tracked point
    (green) and the desired point (magenta cross) drawn on it."""
    import cv2

    img = np.ascontiguousarray(rgb.copy())
    for u, v, _ in np.asarray(detections if detections is not None else np.zeros((0, 3))).reshape(-1, 3):
        cv2.circle(img, (round(u), round(v)), 5, (255, 255, 255), 1, cv2.LINE_AA)
    for i, (u, v) in enumerate(targets if targets is not None else []):
        cv2.circle(img, (round(u), round(v)), 9, (255, 150, 0), 2, cv2.LINE_AA)
        cv2.putText(
            img,
            f"T{i + 1}",
            (round(u) + 10, round(v) - 10),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.7,
            (255, 150, 0),
            2,
            cv2.LINE_AA,
        )
    if desired is not None:
        cv2.drawMarker(
            img, (round(desired[0]), round(desired[1])), (255, 0, 255), cv2.MARKER_CROSS, 28, 2, cv2.LINE_AA
        )
    if track is not None:
        cv2.circle(img, (round(track[0]), round(track[1])), 6, (40, 230, 90), 2, cv2.LINE_AA)
    return img


class EpisodeRunner:
    """Runs one episode against a shared context; call :meth:`run` once."""

    def __init__(
        self,
        ctx: ServoContext,
        spec: EpisodeSpec,
        index: int,
        seed_seq: np.random.SeedSequence,
        recorder: Recorder | None = None,
        *,
        snapshots: bool = False,
    ):
        self.ctx, self.spec, self.index = ctx, spec, index
        self.keep_snapshots = snapshots
        s_frames, s_faults, s_targets = seed_seq.spawn(3)
        self.rng_frames = np.random.default_rng(s_frames)
        self.rng_targets = np.random.default_rng(s_targets)
        self.detector = ctx.make_detector(np.random.default_rng(s_faults))
        self.rec = recorder or Recorder()
        cfg = ctx.suite
        self.controller = (
            IbvsController(ctx.world, ctx.camera, cfg.motion, cfg.ibvs)
            if spec.mode == "ibvs"
            else PbvsController(ctx.world, ctx.camera, cfg.motion, cfg.pbvs)
        )
        self.result = EpisodeResult()
        self.step_index = 0
        self.frame_index = 0
        self.targets: list[Target] = []
        self.pending: list[Target] = []

    # --- sensing -------------------------------------------------------------------------------
    def observe(self) -> Sensed:
        """A frame at the true camera pose, and the detector's output on it (every ``detect_every`` frames)."""
        frame = self.ctx.frames.render(self.ctx.world.world_from_camera(), self.rng_frames)
        self.frame_index += 1
        dropped = False
        det = np.zeros((0, 3))
        if (self.frame_index - 1) % self.ctx.suite.tracker.detect_every == 0:
            det = np.asarray(self.detector.detect(frame.rgb, depth=frame.depth_m), float).reshape(-1, 3)
            det = det[det[:, 2] >= self.ctx.suite.targets.min_score]
            dropped = bool(getattr(self.detector, "dropped", False))
        return Sensed(frame, det, dropped)

    def sense(self) -> Sensed:
        """Observe and update every pending target's tracker."""
        s = self.observe()
        pose = self.controller.camera_pose()
        for t in self.pending:
            motion = self.motion_prediction(t, pose)
            t.state = t.tracker.update(s.frame.rgb, s.detections, motion)
            z = self.crossing_depth(s.frame, t.state.point)
            if np.isfinite(z):
                t.depth_m = z
            elif not np.isfinite(t.depth_m):
                # A crossing always has a surface: no reading means it is nearer than the sensor's range.
                t.depth_m = KINECT_RANGE_M[0] + self.ctx.depth_offset_m
            t.pose = pose
        return s

    def crossing_depth(self, frame: Frame, uv: np.ndarray) -> float:
        """Depth of the crossing under a pixel: the surface reading plus the offset to the crossing point
        (the crossing lies a bar diameter behind the front bar's surface)."""
        z = depth_at(frame.depth_m, uv, window_px=self.ctx.suite.camera.depth_window_px)
        return z + self.ctx.depth_offset_m

    def motion_prediction(self, t: Target, pose_now: np.ndarray) -> tuple[np.ndarray, float] | None:
        """Where the arm's motion since the target's last update moved it (a still point at its pixel and
        depth then), by the controller's own camera pose estimate, and that prediction's sigma (px)."""
        if t.pose is None or not np.isfinite(t.depth_m):
            return None
        cam = self.ctx.camera
        p_prev = cam.back_project(np.atleast_2d(t.tracker.point), np.array([t.depth_m]))[0]
        p_now = apply(rigid_inverse(pose_now) @ t.pose, p_prev)
        shift = float(np.linalg.norm(p_now[:2] - p_prev[:2]))
        sigma = MOTION_SIGMA_PX + cam.fx * shift * DEPTH_SIGMA_M / t.depth_m**2
        return cam.project(p_now)[0], sigma

    def truth(self, crossing_id: int) -> tuple[np.ndarray, np.ndarray]:
        """The true crossing in the camera frame and its true pixel (NaN when there is no true crossing)."""
        if crossing_id < 0:
            return np.full(3, np.nan), np.full(2, np.nan)
        p = apply(rigid_inverse(self.ctx.world.world_from_camera()), self.ctx.rm.crossings.point[crossing_id])
        return p, self.ctx.camera.project(p)[0]

    def hold(self) -> None:
        self.ctx.world.command(np.zeros(6))
        self.ctx.world.step()
        self.step_index += 1

    # --- episode -------------------------------------------------------------------------------
    def run(self, start: StartPose, q_start: np.ndarray) -> EpisodeResult:
        world = self.ctx.world
        world.reset_clock()
        world.reset_joints(q_start)
        if hasattr(self.ctx.frames, "new_sensor"):
            self.ctx.frames.new_sensor(self.rng_frames)
        self.start = start
        self.rec.event(self.step_index, f"episode {self.index}: {self.spec.mode}, start {start.look_at_m}")
        self.acquire()
        if not self.targets:
            self.result.visits.append(
                self._visit_row(0, -1, "no_target", 0, float("nan"), float("nan"), None)
            )
            return self.result
        for k, target in enumerate(self.targets):
            self.visit(k, target)
            self.pending.remove(target)
        return self.result

    def acquire(self) -> None:
        """Detect over a few frames of the still arm, cluster, choose and order the targets, start tracking."""
        cfg = self.ctx.suite.targets
        cam = self.ctx.camera
        frames: list[np.ndarray] = []
        s = None
        for _ in range(3 * cfg.acquire_frames):  # frames with detections; dropped frames do not count
            s = self.observe()
            self.rec.frame(self.step_index, s.frame, s.detections)
            self.rec.state(self.step_index, self.ctx.world)
            if len(s.detections):
                frames.append(s.detections)
            if len(frames) >= cfg.acquire_frames:
                break
            self.hold()
        clusters = persistent_clusters(frames, cfg.cluster_radius_px)
        idx = select_targets(
            clusters.center,
            self.spec.targets,
            desired_px=self.controller.desired_px,
            width=cam.width,
            height=cam.height,
            margin_px=cfg.margin_px,
            row_tolerance_px=cfg.row_tolerance_px,
            rng=self.rng_targets if self.spec.choice == "random" else None,
        )
        pose = self.controller.camera_pose()
        true_T = self.ctx.world.world_from_camera()
        sigma_det = self.ctx.suite.tracker.detection_sigma_px
        for i in idx:
            uv = clusters.center[i]
            tracker = TargetTracker(self.tracker_config())
            tracker.seed(s.frame.rgb, uv, sigma_det / np.sqrt(clusters.count[i]))
            t = Target(uv, self._true_crossing(uv, true_T), tracker, pose=pose)
            z = self.crossing_depth(s.frame, uv)
            t.depth_m = z if np.isfinite(z) else KINECT_RANGE_M[0] + self.ctx.depth_offset_m
            self.targets.append(t)
        self.pending = list(self.targets)
        if self.keep_snapshots and s is not None:
            img = annotate(
                s.frame.rgb,
                detections=frames[-1] if frames else None,
                targets=[t.uv for t in self.targets],
                desired=self.controller.desired_px,
            )
            self.result.snapshots.append(
                (f"{self.spec.mode.upper()} start: {len(self.targets)} targets", img)
            )

    def tracker_config(self) -> TrackerConfig:
        t = self.ctx.suite.tracker
        return TrackerConfig(
            window_px=t.window_px,
            detection_sigma_px=t.detection_sigma_px,
            klt_sigma_px=t.klt_sigma_px,
            klt_motion_fraction=t.klt_motion_fraction,
            gate_px=t.gate_px,
            drift_px=t.drift_px,
        )

    def _true_crossing(self, uv: np.ndarray, world_from_camera: np.ndarray) -> int:
        """The true crossing whose projection is nearest the target pixel, if within the cluster radius."""
        p = apply(rigid_inverse(world_from_camera), self.ctx.rm.crossings.point)
        px = self.ctx.camera.project(np.where((p[:, 2] > 0)[:, None], p, np.nan))
        d = np.linalg.norm(px - uv, axis=1)
        d[~np.isfinite(d)] = np.inf
        i = int(np.argmin(d))
        return i if d[i] <= self.ctx.suite.targets.cluster_radius_px else -1

    # --- one visit -----------------------------------------------------------------------------
    def visit(self, k: int, target: Target) -> None:
        ctx, world, ctl = self.ctx, self.ctx.world, self.controller
        cfg = ctx.suite
        t0_wall, t0_sim = time.perf_counter(), world.time_s
        lost0, reseeds0 = target.tracker.lost_total, target.tracker.reseeds
        ctl.begin()
        self.rec.event(
            self.step_index,
            f"visit {k}: target at ({target.tracker.point[0]:.1f}, {target.tracker.point[1]:.1f}) px",
        )
        if target.crossing_id >= 0:
            self.rec.target(
                self.step_index,
                ctx.rm.crossings.point[target.crossing_id],
                f"T{k + 1}: crossing {target.crossing_id}",
            )

        reason, iterations, settle = "timeout", 0, 0
        initial_px = initial_m = float("nan")
        last = None
        speed_ratio = 0.0
        for it in range(cfg.safety.max_iterations + 1):
            s = self.sense()
            state = target.state
            p_true, uv_true = self.truth(target.crossing_id)
            iterations = it
            blind = target.tracker.frames_since_detection
            if state.lost or blind > cfg.safety.max_blind_frames:
                # Not seen for too long: hold still and look again; give up after max_lost_frames.
                self._record_step(
                    k, it, state, float("nan"), np.zeros(6), 0.0, np.nan, np.nan, p_true, uv_true, s
                )
                self.rec.frame(self.step_index, s.frame, s.detections, track=state, desired=ctl.desired_px)
                if max(blind, target.tracker.lost_frames) > cfg.safety.max_lost_frames:
                    reason = "lost"
                    break
                self.hold()
                settle = 0
                continue
            Z = target.depth_m
            twist, err_px, err_m = ctl.twist(state.point, Z)
            if not np.isfinite(initial_px):
                initial_px, initial_m = err_px, err_m
            last = (state, Z, err_px, err_m, p_true, uv_true)
            self.rec.frame(self.step_index, s.frame, s.detections, track=state, desired=ctl.desired_px)
            known = state.sigma_px <= cfg.safety.converge_sigma_px
            settle = settle + 1 if ctl.converged(err_px, err_m) and known else 0
            stop = None
            if settle >= cfg.safety.settle_frames:
                stop = "converged"
            elif err_px > cfg.safety.divergence_factor * max(initial_px, DIVERGENCE_FLOOR_PX) or (
                ctl.mode == "pbvs"
                and err_m > cfg.safety.divergence_factor * max(initial_m, DIVERGENCE_FLOOR_M)
            ):
                stop = "diverged"
            elif it == cfg.safety.max_iterations:
                stop = "timeout"
            if stop is not None:
                self._record_step(
                    k, it, state, Z, np.zeros(6), ctl.last_gain, err_px, err_m, p_true, uv_true, s
                )
                reason = stop
                if stop == "converged" and self.keep_snapshots:
                    img = annotate(
                        s.frame.rgb, detections=s.detections, track=state.point, desired=ctl.desired_px
                    )
                    self.result.snapshots.append((f"T{k + 1} converged, {it} iterations", img))
                break
            qdot = world.command(ctl.joint_rates(twist))
            self._record_step(k, it, state, Z, twist, ctl.last_gain, err_px, err_m, p_true, uv_true, s, qdot)
            self.rec.state(self.step_index, world)
            world.step()
            self.step_index += 1
            speed_ratio = max(speed_ratio, float(np.max(np.abs(world.qdot) / world.limits.speed)))
            if world.in_contact():
                reason = "collision"
                break
        world.command(np.zeros(6))

        row = self._visit_row(k, target.crossing_id, reason, iterations, initial_px, initial_m, last)
        row.lost_frames = target.tracker.lost_total - lost0
        row.reseeds = target.tracker.reseeds - reseeds0
        self.rec.event(self.step_index, f"visit {k}: {reason} after {iterations} iterations")
        self.rec.scalars_gap(self.step_index)
        if reason == "converged" and cfg.tcp.approach and last is not None:
            speed_ratio = max(speed_ratio, self.tool_move(k, target, last, row))
        row.max_joint_speed_ratio = speed_ratio
        row.max_joint_position_ratio = self._position_ratio(row.episode, k)
        row.wall_s = time.perf_counter() - t0_wall
        row.sim_s = world.time_s - t0_sim
        self.result.visits.append(row)

    def _position_ratio(self, episode: int, k: int) -> float:
        """The largest |q| / limit over the visit's recorded steps (and now)."""
        world = self.ctx.world
        qs = [np.abs(r.q) for r in self.result.steps if r.visit == k]
        qs.append(np.abs(world.q))
        return float(np.max(np.max(qs, axis=0) / world.limits.upper))

    # --- the tool move -------------------------------------------------------------------------
    def tool_move(self, k: int, target: Target, last, row: VisitRow) -> float:
        """Move the tool centre point onto the crossing with the hand-eye transform, measure, come back.

        The crossing's position in the camera frame (back-projected at convergence) is put into the
        tool's frame by ``tcp_from_camera``; the arm then translates the tool there in closed loop on its
        own pose estimate (the kinematic model for IBVS, the measured pose for PBVS), with the camera's
        orientation held, and returns to where it was. Returns the largest joint speed ratio.
        """
        ctx, world, ctl = self.ctx, self.ctx.world, self.controller
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
        iterations, reached, ratio = self._move_camera_to(
            k, goal, "approach", cfg.max_iterations, cfg.tolerance_m
        )
        tcp_true = world.world_from_tcp()
        crossing = (
            ctx.rm.crossings.point[target.crossing_id] if target.crossing_id >= 0 else np.full(3, np.nan)
        )
        axis = tcp_true[:3, 2]
        err = tcp_true[:3, 3] - (crossing - cfg.standoff_m * axis)
        row.tcp_reached = bool(reached)
        row.tcp_error_m = float(np.linalg.norm(err))
        row.tcp_lateral_error_m = float(np.linalg.norm(err - (err @ axis) * axis))
        row.tcp_iterations = iterations
        self.rec.event(
            self.step_index, f"visit {k}: tool on the crossing, true error {row.tcp_error_m * 1000:.2f} mm"
        )
        _, _, back = self._move_camera_to(k, T_before, "retract", cfg.max_iterations, cfg.tolerance_m)
        return max(ratio, back)

    def _move_camera_to(
        self, k: int, goal: np.ndarray, phase: str, max_iterations: int, tol: float
    ) -> tuple[int, bool, float]:
        world, ctl = self.ctx.world, self.controller
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
            self.rec.state(self.step_index, world)
            self._record_motion(k, phase, it, qdot, twist, float(np.linalg.norm(e_cam)))
            world.step()
            self.step_index += 1
            ratio = max(ratio, float(np.max(np.abs(world.qdot) / world.limits.speed)))
        world.command(np.zeros(6))
        return max_iterations, False, ratio

    # --- rows ----------------------------------------------------------------------------------
    def _record_step(
        self, k, it, state: TrackState, Z, twist, gain, err_px, err_m, p_true, uv_true, s: Sensed, qdot=None
    ) -> None:
        ctx, ctl = self.ctx, self.controller
        world = ctx.world
        desired = ctl.desired_px
        true_err_px = float(np.linalg.norm(uv_true - desired))
        lat, err3 = self._true_errors(p_true)
        self.result.steps.append(
            StepRow(
                ctx.suite.name,
                self.index,
                k,
                ctl.mode,
                "servo",
                it,
                world.time_s,
                float(state.point[0]),
                float(state.point[1]),
                float(desired[0]),
                float(desired[1]),
                float(err_px),
                float(err_m),
                float(Z),
                float(uv_true[0]),
                float(uv_true[1]),
                true_err_px,
                lat,
                err3,
                state.source,
                int(len(s.detections)),
                bool(s.dropped),
                float(gain),
                _floats(twist),
                _floats(world.q),
                _floats(qdot if qdot is not None else np.zeros(6)),
                _floats(world.world_from_camera()[:3, 3]),
                _floats(world.world_from_tcp()[:3, 3]),
            )
        )
        self.rec.scalars(
            self.step_index,
            {
                "error_px": err_px,
                "true_error_px": true_err_px,
                "error_mm": err_m * 1000,
                "true_lateral_error_mm": lat * 1000,
                "gain": gain,
            },
        )

    def _record_motion(self, k: int, phase: str, it: int, qdot, twist, err_m: float) -> None:
        world, ctl = self.ctx.world, self.controller
        nan = float("nan")
        self.result.steps.append(
            StepRow(
                self.ctx.suite.name,
                self.index,
                k,
                ctl.mode,
                phase,
                it,
                world.time_s,
                nan,
                nan,
                nan,
                nan,
                nan,
                err_m,
                nan,
                nan,
                nan,
                nan,
                nan,
                nan,
                "none",
                0,
                False,
                0.0,
                _floats(twist),
                _floats(world.q),
                _floats(qdot),
                _floats(world.world_from_camera()[:3, 3]),
                _floats(world.world_from_tcp()[:3, 3]),
            )
        )
        self.rec.scalars(self.step_index, {"tool_move_error_mm": err_m * 1000})

    def _true_errors(self, p_true: np.ndarray) -> tuple[float, float]:
        """True lateral error (to the desired line of sight) and the controller-space error, metres."""
        if not np.all(np.isfinite(p_true)):
            return float("nan"), float("nan")
        want = self.controller.desired_point_camera(p_true[2])
        lateral = float(np.linalg.norm(p_true[:2] - want[:2]))
        if self.controller.mode == "pbvs":
            return lateral, float(np.linalg.norm(p_true - self.controller.desired_point_camera(0.0)))
        return lateral, lateral

    def _visit_row(self, k, crossing_id, reason, iterations, initial_px, initial_m, last) -> VisitRow:
        ctx, ctl = self.ctx, self.controller
        nan = float("nan")
        final_px = final_m = true_px = lat = err3 = depth_err = nan
        if last is not None:
            _, _, final_px, final_m, p_true, uv_true = last
            true_px = float(np.linalg.norm(uv_true - ctl.desired_px))
            lat, err3 = self._true_errors(p_true)
            if ctl.mode == "pbvs" or ctx.suite.ibvs.depth_feature:
                depth_err = float(p_true[2] - ctl.desired_point_camera(ctx.suite.ibvs.desired_depth_m)[2])
        return VisitRow(
            suite=ctx.suite.name,
            episode=self.index,
            visit=k,
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
            lost_frames=0,
            reseeds=0,
            max_joint_speed_ratio=0.0,
            max_joint_position_ratio=0.0,
            wall_s=0.0,
            sim_s=0.0,
            start_standoff_m=float(self.start.standoff_m),
            faults=faults_label(ctx.suite),
        )


def _floats(x) -> list[float]:
    return [float(v) for v in np.asarray(x).reshape(-1)]


def faults_label(suite: SuiteConfig) -> str:
    f = suite.faults
    parts = []
    if f.drop_fraction:
        parts.append(f"drop {f.drop_fraction:.0%}")
    if f.pixel_noise_px:
        parts.append(f"noise {f.pixel_noise_px:g} px")
    if f.spurious_per_frame:
        parts.append(f"spurious {f.spurious_per_frame:g}/frame")
    return ", ".join(parts) or "none"


def faulty(detector: Detector, suite: SuiteConfig, rng: np.random.Generator, camera: Intrinsics) -> Detector:
    """The suite's detector with its faults (or as it is when the suite has none)."""
    f = Faults(suite.faults.drop_fraction, suite.faults.pixel_noise_px, suite.faults.spurious_per_frame)
    if not f.active:
        return detector
    return FaultyDetector(detector, f, rng, width=camera.width, height=camera.height)
