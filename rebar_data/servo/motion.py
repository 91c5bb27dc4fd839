"""From a desired camera twist to joint velocities: saturation, damped least squares, joint speed limits."""

from __future__ import annotations

import numpy as np

from rebar_data.servo.transforms import rotvec


def saturate_twist(twist: np.ndarray, *, speed_m_s: float, rate_rad_s: float) -> np.ndarray:
    """Scale a twist (v, w) uniformly so that |v| <= speed and |w| <= rate (its direction is kept)."""
    t = np.asarray(twist, float)
    scale = max(np.linalg.norm(t[:3]) / speed_m_s, np.linalg.norm(t[3:]) / rate_rad_s, 1.0)
    return t / scale


def damped_pinv_solve(
    J: np.ndarray, twist: np.ndarray, *, damping: float, threshold: float = 0.1
) -> np.ndarray:
    """Joint rates for a twist by damped least squares, damping only near a singularity.

    The damping grows from 0 to ``damping`` as the smallest singular value of J falls below
    ``threshold`` (Nakamura and Hanafusa's scheme), so far from singularities the solution is exact.
    """
    s_min = np.linalg.svd(J, compute_uv=False)[-1]
    mu2 = damping**2 * max(0.0, 1.0 - (s_min / threshold) ** 2)
    return J.T @ np.linalg.solve(J @ J.T + mu2 * np.eye(J.shape[0]), twist)


def limit_joint_speed(qdot: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """Scale joint rates uniformly so that none exceeds its speed limit (the motion's direction is kept)."""
    scale = max(float(np.max(np.abs(qdot) / speed)), 1.0)
    return qdot / scale


def keep_inside_limits(
    qdot: np.ndarray, q: np.ndarray, lower: np.ndarray, upper: np.ndarray, *, dt: float, margin: float
) -> np.ndarray:
    """Stop any joint that would come within ``margin`` of a position limit during the next period."""
    lo = (lower + margin - q) / dt
    hi = (upper - margin - q) / dt
    return np.clip(qdot, np.minimum(lo, 0.0), np.maximum(hi, 0.0))


def orientation_hold(
    world_from_camera: np.ndarray, world_from_reference: np.ndarray, gain: float
) -> np.ndarray:
    """Angular velocity (camera frame) that turns the camera back to a reference orientation."""
    R_err = world_from_camera[:3, :3].T @ world_from_reference[:3, :3]
    return gain * rotvec(R_err)
