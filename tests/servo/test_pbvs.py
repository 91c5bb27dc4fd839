from __future__ import annotations

import numpy as np

from rebar_data.servo import ur5
from rebar_data.servo.ibvs import AdaptiveGain
from rebar_data.servo.pbvs import calibrate_jacobian, pbvs_twist


def test_numerically_calibrated_jacobian_matches_the_model():
    F = np.eye(4)
    F[:3, 3] = [0.0, -0.08, 0.03]
    q = np.array([-0.13, -1.95, -2.35, -1.96, -1.70, 3.14])

    def measure(qq):
        return ur5.forward_kinematics(qq) @ F

    J = calibrate_jacobian(q, measure, perturbation_rad=1e-3)
    np.testing.assert_allclose(J, ur5.jacobian_in_frame(q, F), atol=2e-6)


def test_pbvs_twist_moves_the_camera_towards_the_target():
    twist, e = pbvs_twist(
        np.array([0.02, -0.01, 0.6]), np.array([0.0, 0.0, 0.55]), gain=AdaptiveGain(5, 5, 1)
    )
    np.testing.assert_allclose(e, [0.02, -0.01, 0.05])
    np.testing.assert_allclose(twist, [0.1, -0.05, 0.25, 0, 0, 0])
