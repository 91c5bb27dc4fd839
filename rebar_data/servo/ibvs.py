"""Image-based visual servoing on one point feature (Chaumette and Hutchinson, 2006; ViSP's conventions).

Features are normalised image coordinates ``(x, y) = ((u - cx) / fx, (v - cy) / fy)`` of the tracked
crossing, optionally with ``log(Z / Z*)`` so the camera also holds its standoff (Z from the RGB-D
depth image). The control law is ``v = -lambda(|e|_inf) L+ e`` over the controlled camera axes, with
ViSP's adaptive gain. The point's interaction matrix is the camera's
(:func:`rebar_data.camera.point_interaction_matrix`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rebar_data.camera import point_interaction_matrix
from rebar_data.servo.config import GainConfig


def log_depth_interaction_row(x: float, y: float, Z: float) -> np.ndarray:
    """The 1x6 interaction row of ``log(Z / Z*)`` for a point at (x, y, Z): ``dZ/dt / Z``."""
    return np.array([[0.0, 0.0, -1.0 / Z, -y, x, 0.0]])


@dataclass(frozen=True)
class AdaptiveGain:
    """ViSP's ``vpAdaptiveGain``: ``lambda(x) = a exp(-b x) + c``, from ``at_zero`` (x = 0) down to
    ``at_infinity``, with slope ``slope_at_zero`` at 0. Fast near convergence, gentle far from it."""

    at_zero: float
    at_infinity: float
    slope_at_zero: float

    @staticmethod
    def of(cfg: GainConfig) -> AdaptiveGain:
        return AdaptiveGain(cfg.at_zero, cfg.at_infinity, cfg.slope_at_zero)

    def __call__(self, x: float) -> float:
        a = self.at_zero - self.at_infinity
        if a <= 0:
            return self.at_zero
        return float(a * np.exp(-self.slope_at_zero / a * x) + self.at_infinity)


# Which twist components each option controls (v_x, v_y, v_z, w_x, w_y, w_z).
TRANSLATION = np.array([True, True, True, False, False, False])
ALL_AXES = np.ones(6, bool)


def _features(
    xy: np.ndarray, xy_desired: np.ndarray, Z: float, desired_depth_m: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """The interaction matrix (2 or 3 x 6) and error of the point feature, with log-depth when asked."""
    x, y = float(xy[0]), float(xy[1])
    L = point_interaction_matrix(x, y, Z)
    e = np.asarray(xy, float) - np.asarray(xy_desired, float)
    if desired_depth_m is not None:
        L = np.vstack([L, log_depth_interaction_row(x, y, Z)])
        e = np.append(e, np.log(Z / desired_depth_m))
    return L, e


def ibvs_twist(
    xy: np.ndarray,
    xy_desired: np.ndarray,
    Z: float,
    *,
    gain: AdaptiveGain,
    desired_depth_m: float | None,
    rotation: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Camera twist (6,) and feature error for one point at normalised ``xy`` and depth ``Z``.

    With ``desired_depth_m`` the log-depth feature joins the point. With ``rotation`` False only the
    translation is used (the tool keeps its orientation, as a tying tool must), so ``L`` is taken on
    the translation columns; otherwise on all six (the least-norm twist).
    """
    L, e = _features(xy, xy_desired, Z, desired_depth_m)
    axes = ALL_AXES if rotation else TRANSLATION
    twist = np.zeros(6)
    twist[axes] = -gain(float(np.max(np.abs(e)))) * (np.linalg.pinv(L[:, axes]) @ e)
    return twist, e


def ibvs_twist_aligned(
    xy: np.ndarray,
    xy_desired: np.ndarray,
    Z: float,
    omega: np.ndarray,
    *,
    gain: AdaptiveGain,
    desired_depth_m: float | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Camera twist (6,) and feature error with the rotation ``omega`` (camera frame) given: the translation
    keeps the point feature (and log-depth) decaying as ``-lambda e`` while the camera turns, ``v = L_v+
    (-lambda e - L_w omega)`` (2 1/2 D visual servoing: rotation from the measured pose of the mat, translation
    from the image)."""
    L, e = _features(xy, xy_desired, Z, desired_depth_m)
    lam = gain(float(np.max(np.abs(e))))
    twist = np.zeros(6)
    twist[:3] = np.linalg.pinv(L[:, :3]) @ (-lam * e - L[:, 3:] @ omega)
    twist[3:] = omega
    return twist, e
