"""The tool squared to the mat: the local frame measured from a depth image, the turn it asks, the truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rebar_data.camera import rigid_inverse
from rebar_data.servo.alignment import (
    _two_directions,
    desired_rotation,
    jaw_lines,
    measure_local_frame,
    rotation_error,
)
from rebar_data.servo.config import EpisodeSpec, StartPose, SuiteConfig
from rebar_data.servo.episode import EpisodeRunner
from rebar_data.servo.transforms import apply, from_rotvec
from tests.servo.conftest import suite_dict


def _frame_at(ctx, start: StartPose):
    q, ok = ctx.world.solve_start(ctx.world.camera_pose_for(start))
    assert ok
    ctx.world.reset_joints(q)
    T = ctx.world.world_from_camera()
    return T, ctx.frames.render(T, np.random.default_rng(0))


@pytest.mark.parametrize("tilt", [(0.0, 0.0), (9.0, -7.0)])
def test_the_mat_and_its_bars_are_measured_from_depth_alone(servo_ctx, tilt):
    ctx = servo_ctx
    T, frame = _frame_at(ctx, StartPose(look_at_m=(0.0, 0.0), standoff_m=0.6, tilt_deg=tilt, roll_deg=15.0))
    p = apply(rigid_inverse(T), ctx.rm.crossings.point)
    uv = ctx.camera.project(p)
    inside = np.flatnonzero((uv[:, 0] > 120) & (uv[:, 0] < 520) & (uv[:, 1] > 120) & (uv[:, 1] < 360))
    assert len(inside) >= 4
    d = ctx.depth_offset_m
    for cid in inside[:4]:
        lf = measure_local_frame(frame.depth_m, uv[cid], p[cid, 2] - d, ctx.camera, bar_width_m=d)
        assert lf is not None and lf.bars is not None
        n_true = T[:3, :3].T @ ctx.rm.crossings.normal[cid]
        assert np.degrees(np.arccos(lf.normal @ n_true)) < 0.5  # towards the camera, within half a degree
        for t in (ctx.truth.tangent_a[cid], ctx.truth.tangent_b[cid]):
            t_cam = T[:3, :3].T @ t
            assert min(np.degrees(np.arccos(min(1.0, abs(b @ t_cam)))) for b in lf.bars) < 0.5


def test_the_bars_lines_meet_on_the_crossing(servo_ctx):
    """Fitted to the depth pixels along each bar, the two bars' lines meet within a tenth of a pixel of the
    true crossing, wherever in the window the search started (here 1.8 px off)."""
    ctx = servo_ctx
    T, frame = _frame_at(
        ctx, StartPose(look_at_m=(0.0, 0.0), standoff_m=0.6, tilt_deg=(9.0, -7.0), roll_deg=15.0)
    )
    p = apply(rigid_inverse(T), ctx.rm.crossings.point)
    uv = ctx.camera.project(p)
    inside = np.flatnonzero((uv[:, 0] > 120) & (uv[:, 0] < 520) & (uv[:, 1] > 120) & (uv[:, 1] < 360))
    d = ctx.depth_offset_m
    errors = []
    for cid in inside[:8]:
        lf = measure_local_frame(
            frame.depth_m, uv[cid] + [1.5, -1.0], p[cid, 2] - d, ctx.camera, bar_width_m=d
        )
        assert lf is not None and lf.crossing is not None
        errors.append(np.linalg.norm(ctx.camera.project(lf.crossing[None])[0] - uv[cid]))
    assert len(errors) == 8 and max(errors) < 0.2, errors


def test_a_visit_servos_on_the_lines_once_they_disagree_with_the_detection_for_three_frames():
    from rebar_data.servo.alignment import AlignmentEstimate
    from rebar_data.servo.camera import kinect_intrinsics
    from rebar_data.servo.config import AlignConfig

    cam = kinect_intrinsics()
    pose = np.eye(4)
    est = AlignmentEstimate(cam, AlignConfig(line_switch_px=1.0), depth_offset_m=0.012)
    tracked = np.array([320.0, 240.0])
    assert est.servo_point(tracked, pose) is tracked  # no lines measured yet
    est.world_crossing = cam.back_project(np.array([[320.5, 240.0]]), np.array([0.6]))[0]
    for _ in range(5):  # 0.5 px apart: within the bar, the detection stays
        assert np.array_equal(est.servo_point(tracked, pose), tracked)
    est.world_crossing = cam.back_project(np.array([[322.0, 240.0]]), np.array([0.6]))[0]
    points = [est.servo_point(tracked, pose) for _ in range(3)]
    assert np.array_equal(points[1], tracked) and np.allclose(points[2], [322.0, 240.0])
    assert est.on_lines
    est.world_crossing = cam.back_project(np.array([[320.2, 240.0]]), np.array([0.6]))[0]
    assert np.allclose(est.servo_point(tracked, pose), [320.2, 240.0])  # switched for the rest of the visit
    never = AlignmentEstimate(cam, AlignConfig(line_switch_px=None), depth_offset_m=0.012)
    never.world_crossing = est.world_crossing
    assert all(np.array_equal(never.servo_point(tracked + 5, pose), tracked + 5) for _ in range(5))


def test_no_frame_is_measured_where_no_depth_is():
    from rebar_data.servo.camera import kinect_intrinsics

    cam = kinect_intrinsics()
    assert measure_local_frame(np.zeros((480, 640), np.float32), np.array([320.0, 240.0]), 0.55, cam) is None


def test_the_jaw_takes_the_nearest_bisector_and_the_turn_splits_into_tilt_and_jaw():
    bars = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    lines = jaw_lines(bars, None)
    assert len(lines) == 2 and all(abs(abs(v[0]) - np.sqrt(0.5)) < 1e-9 for v in lines)
    R = desired_rotation(np.array([0.0, 0.0, -1.0]), bars, None)  # the mat square to the camera
    _, tilt, jaw = rotation_error(R)
    assert tilt == pytest.approx(0.0, abs=1e-9) and jaw == pytest.approx(45.0, abs=1e-6)
    at_30 = jaw_lines(bars, 30.0)
    assert any(abs(v @ bars[0] - np.cos(np.radians(30))) < 1e-9 for v in at_30)
    # a mat tilted by 5 degrees about x: the camera's axis must turn 5 degrees
    n = from_rotvec([np.radians(5.0), 0.0, 0.0]) @ np.array([0.0, 0.0, -1.0])
    _, tilt, _ = rotation_error(desired_rotation(n, None, None))
    assert tilt == pytest.approx(5.0, abs=1e-6)


def test_the_truth_scores_a_tool_built_from_it_as_aligned_and_a_turned_one_as_not(servo_ctx):
    truth, cid = servo_ctx.truth, 371
    n, a, b = truth.normal[cid], truth.tangent_a[cid], truth.tangent_b[cid]
    jaw = a + b - ((a + b) @ n) * n
    jaw /= np.linalg.norm(jaw)
    z = -n
    T = np.eye(4)
    T[:3, :3] = np.column_stack([jaw, np.cross(z, jaw), z])
    tilt, jaw_err = truth.errors(cid, T, None)
    assert tilt < 1e-6 and jaw_err < 0.2  # the bars cross at a right angle within the tunnel's curvature
    turned = T.copy()
    turned[:3, :3] = from_rotvec(z * np.radians(10.0)) @ T[:3, :3]
    assert truth.errors(cid, turned, None)[1] == pytest.approx(10.0, abs=0.3)
    assert np.isnan(truth.errors(-1, T, None)[0])


def test_a_tilted_rolled_start_ends_square_to_the_mat_and_tied(servo_ctx):
    suite = SuiteConfig.model_validate(suite_dict())
    ctx = dataclasses.replace(servo_ctx, suite=suite)
    start = StartPose(look_at_m=(0.03, -0.02), standoff_m=0.6, tilt_deg=(12.0, -9.0), roll_deg=25.0)
    q, ok = ctx.world.solve_start(ctx.world.camera_pose_for(start))
    assert ok
    r = EpisodeRunner(
        ctx, EpisodeSpec(mode="ibvs", start=start, targets=1), 0, np.random.SeedSequence(2)
    ).run(start, q)
    v = r.visits[0]
    assert v.converged and v.tied
    assert v.tie_tilt_error_deg < 2.0 and v.tie_jaw_error_deg < 5.0 and v.tcp_lateral_error_m < 0.002
    assert v.tie_crossing_distance_m < 0.005
    phases = [s.phase for s in r.steps]
    dwell = phases.count("tie") * ctx.world.cfg.control_period_s
    assert dwell == pytest.approx(suite.tcp.dwell_s, abs=ctx.world.cfg.control_period_s)


def test_the_second_bar_is_a_peak_of_its_own_not_the_flank_of_a_wide_first_one():
    """A wide bar at 0 degrees spreads its directions over 0-40 degrees, more of them than a thin bar at 90
    degrees gives: the highest bin 30 degrees from the first peak lies on that peak's flank, and the second
    bar is the peak at 90 degrees."""
    rng = np.random.default_rng(0)
    wide = rng.normal(0.0, 18.0, 8000) % 180.0
    thin = rng.normal(90.0, 1.0, 150) % 180.0
    theta = np.concatenate([wide, thin])
    p1, p2 = _two_directions(theta, np.ones_like(theta), 30.0)
    assert min(p1, 180 - p1) <= 4
    assert abs(p2 - 90) <= 2, p2
    assert _two_directions(wide, np.ones_like(wide), 30.0) is None  # one bar: no second peak
