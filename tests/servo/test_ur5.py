from __future__ import annotations

import numpy as np

from rebar_data.camera import rigid_inverse
from rebar_data.servo import ur5


def test_zero_pose_is_the_dh_table_sum():
    """At zero the arm is stretched along -x: x = a2 + a3, y = -(d4 + d6), z = d1 - d5, tool along -y."""
    T = ur5.forward_kinematics(np.zeros(6))
    d, a = ur5.D_M, ur5.A_M
    np.testing.assert_allclose(T[:3, 3], [a[1] + a[2], -(d[3] + d[5]), d[0] - d[4]], atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [0.0, -1.0, 0.0], atol=1e-12)


def test_forward_kinematics_is_the_product_of_dh_transforms():
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = rng.uniform(-np.pi, np.pi, 6)
        T = np.eye(4)
        for i in range(6):
            ct, st = np.cos(q[i]), np.sin(q[i])
            ca, sa = np.cos(ur5.ALPHA_RAD[i]), np.sin(ur5.ALPHA_RAD[i])
            Rz = np.array([[ct, -st, 0, 0], [st, ct, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
            Tz = np.eye(4)
            Tz[2, 3] = ur5.D_M[i]
            Tx = np.eye(4)
            Tx[0, 3] = ur5.A_M[i]
            Rx = np.array([[1, 0, 0, 0], [0, ca, -sa, 0], [0, sa, ca, 0], [0, 0, 0, 1]])
            T = T @ Rz @ Tz @ Tx @ Rx
        np.testing.assert_allclose(ur5.forward_kinematics(q), T, atol=1e-12)


def test_simulated_arm_from_the_written_urdf_matches_the_dh_kinematics(servo_ctx):
    world = servo_ctx.world
    rng = np.random.default_rng(1)
    for _ in range(4):
        q = rng.uniform(-2.5, 2.5, 6)
        world.reset_joints(q)
        flange = rigid_inverse(world.layout.world_from_base) @ world.world_from_link(6)
        np.testing.assert_allclose(flange, ur5.forward_kinematics(q), atol=2e-6)
        np.testing.assert_allclose(world.world_from_camera(), world.world_from_camera_model(q), atol=2e-6)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(2)
    F = np.eye(4)
    F[:3, 3] = [0.0, -0.08, 0.03]
    q = rng.uniform(-2, 2, 6)
    J = ur5.jacobian(q, F)
    eps = 1e-6
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = eps
        Tp, Tm = ur5.forward_kinematics(q + dq) @ F, ur5.forward_kinematics(q - dq) @ F
        np.testing.assert_allclose(J[:3, j], (Tp[:3, 3] - Tm[:3, 3]) / (2 * eps), atol=1e-7)
        dR = (Tp[:3, :3] - Tm[:3, :3]) / (2 * eps) @ ur5.forward_kinematics(q)[:3, :3].T
        np.testing.assert_allclose(J[3:, j], [dR[2, 1], dR[0, 2], dR[1, 0]], atol=1e-7)


def test_inverse_kinematics_round_trip():
    q0 = np.array([0.3, -1.4, -2.0, -2.6, -1.2, 3.0])
    target = ur5.forward_kinematics(q0)
    q, ok = ur5.inverse_kinematics(target, q0 + 0.2)
    assert ok
    np.testing.assert_allclose(ur5.forward_kinematics(q), target, atol=1e-6)


def test_urdf_has_the_published_limits_and_masses():
    text = ur5.ur5_urdf()
    assert text.count('type="revolute"') == 6
    assert f'velocity="{np.pi:.9g}"' in text
    assert f'lower="{-2 * np.pi:.9g}"' in text
    for m in ur5.MASS_KG:
        assert f'<mass value="{m:.6g}"/>' in text
