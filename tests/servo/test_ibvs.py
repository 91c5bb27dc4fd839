from __future__ import annotations

import numpy as np
import pytest

from rebar_data.camera import point_interaction_matrix
from rebar_data.servo.ibvs import AdaptiveGain, ibvs_twist, log_depth_interaction_row
from rebar_data.servo.transforms import from_rotvec


def _move(point_camera: np.ndarray, twist: np.ndarray, dt: float) -> np.ndarray:
    """A still point seen from a camera that moves by ``twist`` (camera frame) for ``dt``."""
    R = from_rotvec(twist[3:] * dt)
    t = twist[:3] * dt
    return R.T @ (point_camera - t)


@pytest.mark.parametrize("P", [[0.05, -0.03, 0.55], [-0.2, 0.1, 0.8], [0.0, 0.0, 0.5]])
def test_interaction_matrices_match_finite_differences(P):
    P = np.array(P)
    x, y, Z = P[0] / P[2], P[1] / P[2], P[2]
    L = np.vstack([point_interaction_matrix(x, y, Z), log_depth_interaction_row(x, y, Z)])
    eps = 1e-6
    for j in range(6):
        v = np.zeros(6)
        v[j] = 1.0
        p, m = _move(P, v, eps), _move(P, -v, eps)

        def s(q):
            return np.array([q[0] / q[2], q[1] / q[2], np.log(q[2])])

        np.testing.assert_allclose(L[:, j], (s(p) - s(m)) / (2 * eps), atol=1e-6)


def test_adaptive_gain_matches_visp():
    g = AdaptiveGain(4.0, 0.4, 30.0)
    assert g(0.0) == pytest.approx(4.0)
    assert g(1e6) == pytest.approx(0.4)
    h = 1e-7
    assert (g(h) - g(0.0)) / h == pytest.approx(-30.0, rel=1e-4)


@pytest.mark.parametrize("rotation", [False, True])
def test_ibvs_on_a_synthetic_point_converges(rotation):
    P = np.array([0.06, -0.04, 0.7])  # the target, in the camera frame
    desired = np.zeros(2)
    gain = AdaptiveGain(8.0, 3.0, 30.0)
    errors = []
    for _ in range(60):
        xy = P[:2] / P[2]
        twist, e = ibvs_twist(xy, desired, P[2], gain=gain, desired_depth_m=0.55, rotation=rotation)
        errors.append(np.linalg.norm(e))
        P = _move(P, twist, 0.032)
    assert errors[-1] < 1e-4 * errors[0]
    assert np.all(np.diff(errors) < 1e-12)  # the error never grows
    assert P[2] == pytest.approx(0.55, abs=1e-4)
