"""Position-based visual servoing with a numerically calibrated Jacobian, as the paper does it.

The target crossing is back-projected to 3D in the camera frame from its pixel and the RGB-D depth;
the error is its offset from the desired position (on the optical axis at the standoff), and the camera
moves along it, ``v = lambda(|e|_inf) e``. Joint rates come from a Jacobian measured on the arm itself:
each joint is perturbed by a small angle and the camera's displacement read back, so the controller uses
no kinematic model of the robot (it would work the same with an unknown arm).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from rebar_data.servo.ibvs import AdaptiveGain
from rebar_data.servo.transforms import rotvec


def calibrate_jacobian(
    q: np.ndarray, measure: Callable[[np.ndarray], np.ndarray], *, perturbation_rad: float
) -> np.ndarray:
    """6x6 Jacobian from joint rates to the camera's twist in its own frame, by central differences.

    ``measure(q)`` returns the camera pose ``world_from_camera`` with the arm at ``q``. Column ``j`` is
    the camera's displacement (translation, rotation vector), in the camera frame at ``q``, when joint
    ``j`` turns by ``+-perturbation_rad``, divided by twice the perturbation.
    """
    T0 = measure(q)
    R0 = T0[:3, :3]
    J = np.empty((6, 6))
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = perturbation_rad
        Tp, Tm = measure(q + dq), measure(q - dq)
        J[:3, j] = R0.T @ (Tp[:3, 3] - Tm[:3, 3]) / (2 * perturbation_rad)
        J[3:, j] = (rotvec(R0.T @ Tp[:3, :3]) - rotvec(R0.T @ Tm[:3, :3])) / (2 * perturbation_rad)
    return J


def pbvs_twist(
    point_camera: np.ndarray, desired_m: np.ndarray, *, gain: AdaptiveGain, omega: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Camera twist (6,) and the 3D error ``p - p*`` for a target at ``point_camera``: no rotation, or the
    rotation ``omega`` (camera frame) with the translation that keeps ``e`` decaying as ``-lambda e`` while the
    camera turns (a still point moves as ``dp/dt = -v - omega x p``, so ``v = lambda e - omega x p``)."""
    p = np.asarray(point_camera, float)
    e = p - np.asarray(desired_m, float)
    twist = np.zeros(6)
    twist[:3] = gain(float(np.max(np.abs(e)))) * e
    if omega is not None:
        twist[:3] -= np.cross(omega, p)
        twist[3:] = omega
    return twist, e
