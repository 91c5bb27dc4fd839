from __future__ import annotations

import numpy as np
import pytest

from rebar_data.servo.config import StartPose


def test_control_period_keeps_to_the_32_ms_grid(servo_ctx):
    world = servo_ctx.world
    steps0, ctrl0 = world.physics_steps, world.control_steps
    for _ in range(25):
        world.step()
    # 25 periods of 32 ms at 240 Hz: 192 physics steps, never drifting
    assert world.physics_steps - steps0 == round((ctrl0 + 25) * 0.032 * 240) - round(ctrl0 * 0.032 * 240)


def test_joint_velocity_command_is_followed(servo_ctx):
    world = servo_ctx.world
    q0, ok = world.solve_start(world.camera_pose_for(StartPose()))
    world.reset_joints(q0)
    qdot = np.array([0.1, -0.05, 0.08, 0.0, 0.1, -0.2])
    for _ in range(10):
        world.command(qdot)
        world.step()
    np.testing.assert_allclose(world.q - q0, qdot * 0.32, atol=2e-3)


def test_no_joint_ever_passes_its_limit(servo_ctx):
    world = servo_ctx.world
    q0, _ = world.solve_start(world.camera_pose_for(StartPose()))
    q = q0.copy()
    q[5] = 2 * np.pi - 0.05  # wrist 3 near its upper limit
    world.reset_joints(q)
    for _ in range(20):
        sent = world.command(np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.pi]))
        world.step()
        assert world.q[5] <= 2 * np.pi + 1e-3
    assert 0.0 <= sent[5] < 0.2  # slowed from pi rad/s to almost nothing at the limit


def test_start_poses_look_at_the_mesh_from_the_standoff(servo_ctx):
    world = servo_ctx.world
    start = StartPose(look_at_m=(0.05, -0.05), standoff_m=0.55, tilt_deg=(4.0, -3.0), roll_deg=8.0)
    T = world.camera_pose_for(start)
    p, n = world.surface_point(0.05, -0.05)
    assert np.linalg.norm(p - T[:3, 3]) == pytest.approx(0.55)
    np.testing.assert_allclose((p - T[:3, 3]) / 0.55, T[:3, 2], atol=1e-12)  # on the optical axis
    q, ok = world.solve_start(T)
    assert ok
    world.reset_joints(q)
    np.testing.assert_allclose(world.world_from_camera(), T, atol=1e-5)
    assert not world.in_contact()


def test_an_arm_link_in_the_floor_is_a_collision_and_out_of_reach(servo_ctx):
    """With its base lowered a metre (a lift at the segment's lower edge), the arm looking up at the segment
    from a tilted view would reach into the floor: the reach check refuses it, and its contact counts."""
    world = servo_ctx.world
    start = StartPose(look_at_m=(-1.3, -1.0), standoff_m=0.6, tilt_deg=(10.6, -10.6), roll_deg=30.0)
    low = world.surface_point(*start.look_at_m)[0] - world.surface_point(0.0, 0.0)[0]
    assert low[2] < -0.9
    try:
        world.move_base(low)
        q, ok = world.solve_start(world.camera_pose_for(start))
        assert ok  # the joints exist: inverse kinematics alone would take it
        assert not world.clear_at(q)
        world.reset_joints(q)
        world.client.performCollisionDetection()
        assert world.in_contact()
        square = StartPose(look_at_m=(-1.3, -1.0), standoff_m=0.6)
        q_square, ok = world.solve_start(world.camera_pose_for(square))
        assert ok and world.clear_at(q_square)  # looking square at the same point clears the floor
    finally:
        world.move_base(np.zeros(3))
        q0, _ = world.solve_start(world.camera_pose_for(StartPose()))
        world.reset_joints(q0)
