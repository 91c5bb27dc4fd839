from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from rebar_data.servo.camera import depth_at, kinect_intrinsics


def test_kinect_field_of_view_is_57_degrees_with_square_pixels():
    cam = kinect_intrinsics()
    assert cam.fx == cam.fy == pytest.approx(589.4, abs=0.05)
    assert cam.fov_deg[0] == pytest.approx(57.0)
    assert (cam.width, cam.height, cam.cx, cam.cy) == (640, 480, 320.0, 240.0)


def test_the_robots_default_depth_sensor_keeps_the_kinect_noise_range_and_quantisation():
    """The suite's default depth sensor (structured light at its nominal parameters) reads a plane at 2 m
    with Nguyen's axial noise and 1/8 px disparity steps of the 75 mm, 580 px pair, and nothing outside
    0.5-4.5 m."""
    from rebar_data.render.depth_sensor import kinect_sigma_m, sense_depth
    from rebar_data.scene.sample import nominal_depth_sensor
    from rebar_data.servo.config import RobotCameraConfig

    cam = kinect_intrinsics()
    s = nominal_depth_sensor(RobotCameraConfig().depth_sensor)
    assert (s.model, s.baseline_m, s.focal_px, s.disparity_step_px) == (
        "structured_light",
        0.075,
        580.0,
        0.125,
    )
    rng = np.random.default_rng(0)
    out = sense_depth(np.full((200, 200), 2.0, np.float32), s, rng, fx=cam.fx)
    step = 2.0**2 / (580 * 0.075 * 8)  # one 1/8 px disparity step at 2 m
    assert out.std() == pytest.approx(np.hypot(kinect_sigma_m(2.0), step / np.sqrt(12)), rel=0.05)
    assert abs(out.mean() - 2.0) < 0.002
    quiet = nominal_depth_sensor("structured_light", noise=False)
    ramp = np.tile(np.linspace(3.0, 3.2, 500, dtype=np.float32), (20, 1))
    steps = np.diff(np.unique(sense_depth(ramp, replace(quiet, window_px=1), rng, fx=cam.fx)[:, 100:]))
    assert steps.min() > 0.02  # quantised: ~z^2 / 346 at 3 m
    near_far = np.tile(np.array([0.3, 5.0, 0.0], np.float32).repeat(40), (20, 1))
    assert np.all(sense_depth(near_far, s, rng, fx=cam.fx) == 0)  # out of range: no reading


def test_depth_at_uses_only_valid_pixels():
    d = np.zeros((10, 10), np.float32)
    d[4:7, 4:7] = 0.6
    assert depth_at(d, np.array([5.5, 5.5])) == pytest.approx(0.6)
    assert np.isnan(depth_at(d, np.array([0.5, 0.5]), window_px=3))


def test_depth_at_reads_the_front_surface_through_holes():
    # a bar at 0.60 m over 6 of the window's 25 pixels, the ground at 1.25 m through its holes
    d = np.full((11, 11), 1.25)
    d[3:8, 5] = 0.60
    d[5, 4] = 0.605
    assert depth_at(d, np.array([5.5, 5.5])) == pytest.approx(1.25)
    assert depth_at(d, np.array([5.5, 5.5]), front_band_m=0.017) == pytest.approx(0.60)
