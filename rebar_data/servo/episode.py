"""One episode: start pose, target acquisition, then each target visited in turn (servo, tool move, back).

Every control step is: frame -> detections -> every pending target's tracker -> the controller on the
current target -> joint velocities -> one control period of physics. All targets of the episode are
tracked from acquisition on, so each one has averaged its detections before its visit starts.

Safety is part of the loop: a lost target holds the arm still until it is seen again (or the visit ends
as ``lost``); an error growing past ``divergence_factor`` times its start ends the visit as
``diverged``; contact with the mesh or the table ends it as ``collision``; every command is clipped so
that no joint passes its speed or position limit.

The parts, one module each: what the episode sees (:mod:`~rebar_data.servo.sensing`), a visit's control
loop (:mod:`~rebar_data.servo.control`), its rows (:mod:`~rebar_data.servo.rows`), what goes to a
recording (:mod:`~rebar_data.servo.recorder`) and the report's annotated views
(:mod:`~rebar_data.servo.drawing`).
"""

from __future__ import annotations

import numpy as np

from rebar_data.servo import control
from rebar_data.servo.config import EpisodeSpec, StartPose
from rebar_data.servo.context import ServoContext
from rebar_data.servo.controllers import Controller, IbvsController, PbvsController
from rebar_data.servo.drawing import annotate
from rebar_data.servo.recorder import Recorder
from rebar_data.servo.records import EpisodeResult
from rebar_data.servo.rows import EpisodeRows
from rebar_data.servo.sensing import Sensed, Sensing, Target
from rebar_data.servo.targets import persistent_clusters, select_targets
from rebar_data.servo.tracker import TargetTracker


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
        detector = ctx.make_detector(np.random.default_rng(s_faults))
        self.rec = recorder or Recorder()
        cfg = ctx.suite
        self.controller: Controller = (
            IbvsController(ctx.world, ctx.camera, cfg.motion, cfg.ibvs)
            if spec.mode == "ibvs"
            else PbvsController(ctx.world, ctx.camera, cfg.motion, cfg.pbvs)
        )
        self.sensing = Sensing(ctx, detector, self.rng_frames, self.controller.camera_pose)
        self.result = EpisodeResult()
        self.step_index = 0
        self.targets: list[Target] = []
        self.pending: list[Target] = []

    def hold(self) -> None:
        """Command the arm still for one control period."""
        self.ctx.world.command(np.zeros(6))
        self.ctx.world.step()
        self.step_index += 1

    def begin(self, start: StartPose, q_start: np.ndarray) -> None:
        """The episode's start: its own clock, the arm at ``q_start``, a new camera sensor, its row builder."""
        world = self.ctx.world
        world.reset_clock()
        world.reset_joints(q_start)
        if self.ctx.new_sensor is not None:
            self.ctx.new_sensor(self.rng_frames)
        self.rows: EpisodeRows = EpisodeRows(
            self.ctx, self.controller, episode=self.index, start_standoff_m=start.standoff_m
        )

    def run(self, start: StartPose, q_start: np.ndarray) -> EpisodeResult:
        self.begin(start, q_start)
        self.rec.event(self.step_index, f"episode {self.index}: {self.spec.mode}, start {start.look_at_m}")
        self.acquire()
        if not self.targets:
            self.result.visits.append(
                self.rows.visit(
                    visit=0,
                    crossing_id=-1,
                    reason="no_target",
                    iterations=0,
                    initial_px=float("nan"),
                    initial_m=float("nan"),
                    last=None,
                )
            )
            return self.result
        for k, target in enumerate(self.targets):
            control.visit(self, k, target)
            self.pending.remove(target)
        return self.result

    def still_frames(self, n: int) -> tuple[list[np.ndarray], Sensed | None]:
        """Frames of the still arm until ``n`` have detections (dropped frames do not count; at most 3n
        frames): their detections, and the last frame sensed."""
        frames: list[np.ndarray] = []
        s = None
        for _ in range(3 * n):
            s = self.sensing.observe()
            self.rec.frame(self.step_index, s.frame, s.detections)
            self.rec.state(self.step_index, self.ctx.world)
            if len(s.detections):
                frames.append(s.detections)
            if len(frames) >= n:
                break
            self.hold()
        return frames, s

    def acquire(self) -> None:
        """Detect over a few frames of the still arm, cluster, choose and order the targets, start tracking."""
        cfg = self.ctx.suite.targets
        cam = self.ctx.camera
        frames, s = self.still_frames(cfg.acquire_frames)
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
            tracker = TargetTracker(self.ctx.suite.tracker)
            tracker.seed(s.frame.rgb, uv, sigma_det / np.sqrt(clusters.count[i]))
            t = Target(uv=uv, crossing_id=self.sensing.true_crossing(uv, true_T), tracker=tracker, pose=pose)
            z = self.sensing.crossing_depth(s.frame, uv)
            t.depth_m = z if np.isfinite(z) else self.sensing.nearest_depth_m()
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
