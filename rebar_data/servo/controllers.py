"""IBVS and PBVS as controllers of the arm: from a tracked image point and depth to joint velocities.

Both share one interface so the visit loop is the same for either:
- IBVS knows the UR5's kinematic model: the camera twist becomes joint rates through the model's
  Jacobian, and the camera pose it needs (re-identifying targets, the tool move) comes from forward
  kinematics.
- PBVS knows no model: it measures the camera pose on the arm and calibrates its Jacobian numerically
  (every ``recalibrate_every`` steps).
Each holds the tool's orientation at the start of the visit unless IBVS is told to rotate.
"""

from __future__ import annotations

import numpy as np

from rebar_data.camera import Intrinsics
from rebar_data.servo import ur5
from rebar_data.servo.config import IbvsConfig, MotionConfig, PbvsConfig
from rebar_data.servo.ibvs import AdaptiveGain, ibvs_twist, ibvs_twist_aligned
from rebar_data.servo.motion import (
    damped_pinv_solve,
    keep_inside_limits,
    limit_joint_speed,
    orientation_hold,
    saturate_twist,
)
from rebar_data.servo.pbvs import calibrate_jacobian, pbvs_twist
from rebar_data.servo.world import ServoWorld


class _Base:
    """``drives_position``: the controller drives the target's 3D point in the camera frame (its metric
    error is that point's error), not its image point. ``drives_depth``: it drives the target's depth."""

    mode = ""
    drives_position = False

    def __init__(self, world: ServoWorld, camera: Intrinsics, motion: MotionConfig):
        self.world, self.camera, self.motion = world, camera, motion
        self.drives_depth = False
        self.reference: np.ndarray | None = None
        self.hold_orientation = True
        self.last_gain = 0.0

    def begin(self) -> None:
        """Start a visit: the tool's current orientation is the one to hold."""
        self.reference = self.camera_pose()

    def camera_pose(self) -> np.ndarray:
        raise NotImplementedError

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """Joint rates to the camera's twist in the camera frame."""
        raise NotImplementedError

    def joint_rates(
        self, twist: np.ndarray, *, hold: bool | None = None, speed_m_s: float | None = None
    ) -> np.ndarray:
        """Joint velocities for a camera twist: orientation hold added (``hold``: the controller's own rule
        unless given), saturated (at ``speed_m_s``, the suite's camera speed unless given), damped, limited."""
        m = self.motion
        t = np.array(twist, float)
        hold = self.hold_orientation if hold is None else hold
        if hold and self.reference is not None:
            t[3:] = orientation_hold(self.camera_pose(), self.reference, m.orientation_gain)
        speed = m.camera_speed_m_s if speed_m_s is None else speed_m_s
        t = saturate_twist(t, speed_m_s=speed, rate_rad_s=m.camera_rate_rad_s)
        q = self.world.q
        qdot = damped_pinv_solve(self.jacobian(q), t, damping=m.damping)
        lim = self.world.limits
        qdot = limit_joint_speed(qdot, lim.speed)
        return keep_inside_limits(
            qdot, q, lim.lower, lim.upper, dt=self.world.cfg.control_period_s, margin=m.joint_margin_rad
        )


class IbvsController(_Base):
    mode = "ibvs"

    def __init__(self, world: ServoWorld, camera: Intrinsics, motion: MotionConfig, cfg: IbvsConfig):
        super().__init__(world, camera, motion)
        self.cfg = cfg
        self.gain = AdaptiveGain.of(cfg.gain)
        self.hold_orientation = not cfg.rotation
        self.drives_depth = cfg.depth_feature
        self.desired_px = np.array(cfg.desired_px) if cfg.desired_px is not None else camera.principal_point

    def camera_pose(self) -> np.ndarray:
        return self.world.world_from_camera_model(self.world.q)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        return ur5.jacobian_in_frame(q, self.world.layout.flange_from_camera)

    def twist(
        self, uv: np.ndarray, Z: float, omega: np.ndarray | None = None
    ) -> tuple[np.ndarray, float, float]:
        """Twist, image error (px) and lateral error (m) for the tracked point at depth Z; with ``omega`` (the
        alignment's rotation, camera frame) the camera turns so while the point keeps to its path."""
        cam = self.camera
        xy = cam.normalized(uv)[0]
        xy_star = cam.normalized(self.desired_px)[0]
        depth = self.cfg.desired_depth_m if self.cfg.depth_feature else None
        if omega is not None:
            twist, e = ibvs_twist_aligned(xy, xy_star, Z, omega, gain=self.gain, desired_depth_m=depth)
        else:
            twist, e = ibvs_twist(
                xy, xy_star, Z, gain=self.gain, desired_depth_m=depth, rotation=self.cfg.rotation
            )
        self.last_gain = self.gain(float(np.max(np.abs(e))))
        error_px = float(np.linalg.norm(np.asarray(uv) - self.desired_px))
        return twist, error_px, float(np.linalg.norm(e[:2]) * Z)

    def converged(self, error_px: float, error_m: float) -> bool:
        return error_px < self.cfg.converge_px

    def desired_point_camera(self, Z: float) -> np.ndarray:
        """Where the target should be in the camera frame at depth Z (on the desired line of sight)."""
        xy = self.camera.normalized(self.desired_px)[0]
        return np.array([xy[0] * Z, xy[1] * Z, Z])


class PbvsController(_Base):
    mode = "pbvs"
    drives_position = True

    def __init__(self, world: ServoWorld, camera: Intrinsics, motion: MotionConfig, cfg: PbvsConfig):
        super().__init__(world, camera, motion)
        self.cfg = cfg
        self.drives_depth = True
        self.gain = AdaptiveGain.of(cfg.gain)
        self.desired_m = np.array(cfg.desired_m, float)
        self.desired_px = camera.project(self.desired_m)[0]
        self._J: np.ndarray | None = None
        self._calls = 0
        self.calibrations = 0

    def begin(self) -> None:
        super().begin()
        self._J, self._calls = None, 0

    def camera_pose(self) -> np.ndarray:
        return self.world.world_from_camera()

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        if self._J is None or self._calls % self.cfg.recalibrate_every == 0:
            self._J = calibrate_jacobian(
                q, self.world.measure_camera_after, perturbation_rad=self.cfg.perturbation_rad
            )
            self.calibrations += 1
        self._calls += 1
        return self._J

    def twist(
        self, uv: np.ndarray, Z: float, omega: np.ndarray | None = None
    ) -> tuple[np.ndarray, float, float]:
        p = self.camera.back_project(np.atleast_2d(uv), np.array([Z]))[0]
        twist, e = pbvs_twist(p, self.desired_m, gain=self.gain, omega=omega)
        self.last_gain = self.gain(float(np.max(np.abs(e))))
        error_px = float(np.linalg.norm(np.asarray(uv) - self.desired_px))
        return twist, error_px, float(np.linalg.norm(e))

    def converged(self, error_px: float, error_m: float) -> bool:
        return error_m < self.cfg.converge_m

    def desired_point_camera(self, Z: float) -> np.ndarray:
        return self.desired_m.copy()


Controller = IbvsController | PbvsController
