"""What an episode sees: camera frames, the detector's output on them, and every pending target's tracker.

Also the simulator's ground truth about a target (for the rows, never for control).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rebar_data.camera import rigid_inverse
from rebar_data.servo.camera import KINECT_RANGE_M, depth_at
from rebar_data.servo.context import ServoContext
from rebar_data.servo.detectors import ServoDetector
from rebar_data.servo.frames import CameraFrame
from rebar_data.servo.tracker import TargetTracker, TrackState
from rebar_data.servo.transforms import apply

# Frame-to-frame accuracy of the arm's own motion prediction of a still point: a floor, plus the pixel
# error that a depth error of DEPTH_SIGMA_M makes of the camera's lateral motion.
MOTION_SIGMA_PX = 0.02
DEPTH_SIGMA_M = 0.002
# The depth sensor's noise allowed on the front surface of a depth window (m).
FRONT_NOISE_M = 0.005


@dataclass(kw_only=True)
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
class Sensed:
    """One frame, its detections (N, 3) above the suite's score floor, and whether a fault dropped them."""

    frame: CameraFrame
    detections: np.ndarray
    dropped: bool


class Sensing:
    """The camera and the detector of one episode; ``camera_pose`` is the controller's pose estimate."""

    def __init__(
        self,
        ctx: ServoContext,
        detector: ServoDetector,
        rng: np.random.Generator,
        camera_pose: Callable[[], np.ndarray],
    ):
        self.ctx, self.detector, self.rng = ctx, detector, rng
        self.camera_pose = camera_pose
        self.frame_index = 0

    def observe(self) -> Sensed:
        """A frame at the true camera pose, and the detector's output on it (every ``detect_every`` frames)."""
        frame = self.ctx.frames.render(self.ctx.world.world_from_camera(), self.rng)
        self.frame_index += 1
        dropped = False
        det = np.zeros((0, 3))
        if (self.frame_index - 1) % self.ctx.suite.tracker.detect_every == 0:
            det = np.asarray(self.detector.detect(frame.rgb, depth=frame.depth_m), float).reshape(-1, 3)
            det = det[det[:, 2] >= self.ctx.suite.targets.min_score]
            dropped = bool(self.detector.dropped)
        return Sensed(frame, det, dropped)

    def sense(self, pending: list[Target]) -> Sensed:
        """Observe and update every pending target's tracker."""
        s = self.observe()
        pose = self.camera_pose()
        for t in pending:
            motion = self.motion_prediction(t, pose)
            t.state = t.tracker.update(s.frame.rgb, s.detections, motion)
            z = self.crossing_depth(s.frame, t.state.point)
            if np.isfinite(z):
                t.depth_m = z
            elif not np.isfinite(t.depth_m):
                # A crossing always has a surface: no reading means it is nearer than the sensor's range.
                t.depth_m = self.nearest_depth_m()
            t.pose = pose
        return s

    def nearest_depth_m(self) -> float:
        """The crossing depth taken where the sensor reads none: its near limit (plus the crossing offset)."""
        return KINECT_RANGE_M[0] + self.ctx.depth_offset_m

    def crossing_depth(self, frame: CameraFrame, uv: np.ndarray) -> float:
        """Depth of the crossing under a pixel: the surface reading plus the offset to the crossing point
        (the crossing lies a bar diameter behind the front bar's surface). Only the window's front surface is
        read (the front bar and the one under it, within a diameter and the sensor's noise), never the
        lower mat or the ground seen through the bar's holes."""
        offset = self.ctx.depth_offset_m
        z = depth_at(
            frame.depth_m,
            uv,
            window_px=self.ctx.suite.camera.depth_window_px,
            front_band_m=offset + FRONT_NOISE_M,
        )
        return z + offset

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

    def true_crossing(self, uv: np.ndarray, world_from_camera: np.ndarray) -> int:
        """The true crossing whose projection is nearest the target pixel, if within the cluster radius."""
        p = apply(rigid_inverse(world_from_camera), self.ctx.rm.crossings.point)
        px = self.ctx.camera.project(np.where((p[:, 2] > 0)[:, None], p, np.nan))
        d = np.linalg.norm(px - uv, axis=1)
        d[~np.isfinite(d)] = np.inf
        i = int(np.argmin(d))
        return i if d[i] <= self.ctx.suite.targets.cluster_radius_px else -1
