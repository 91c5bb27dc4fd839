from __future__ import annotations

import numpy as np
import pytest

from rebar_data.config import ConfigError
from rebar_data.servo.config import StartPose
from rebar_data.servo.detectors import Faults, FaultyDetector, GroundTruthDetector, load_shipped_detector


class _Fixed:
    def __init__(self, det):
        self.det = np.asarray(det, float)

    def detect(self, rgb, *, depth=None):
        return self.det.copy()


def test_ground_truth_detector_projects_the_visible_crossings(servo_ctx):
    ctx = servo_ctx
    world = ctx.world
    q, ok = world.solve_start(world.camera_pose_for(StartPose(look_at_m=(0.0, 0.0), standoff_m=0.6)))
    assert ok
    world.reset_joints(q)
    gt = GroundTruthDetector(ctx.rm, ctx.camera, ctx.frames.cast_rays, world.world_from_camera)
    det = gt.detect(np.zeros((480, 640, 3), np.uint8))
    assert 20 <= len(det) <= 60  # a 100 mm grid seen from 0.6 m with a 57 x 44 degree view
    # each detection is the exact projection of its crossing's own point (the tying target)
    T = np.linalg.inv(world.world_from_camera())
    p = ctx.rm.crossings.point[gt.last_crossing_ids] @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(det[:, :2], ctx.camera.project(p), atol=1e-6)
    # and a look at the rendered depth confirms a bar surface is there, about a bar diameter in front
    frame = ctx.frames.render(world.world_from_camera(), np.random.default_rng(0))
    for (u, v, _), z in zip(det[:5], p[:5, 2], strict=True):
        assert frame.depth_m[int(v), int(u)] == pytest.approx(z - 0.012, abs=0.004)


def test_faults_drop_noise_and_spurious_hits():
    truth = np.array([[100.0, 100.0, 1.0], [300.0, 200.0, 1.0]])
    f = FaultyDetector(_Fixed(truth), Faults(0.3, 2.0, 1.0), np.random.default_rng(0), width=640, height=480)
    dropped, errors, extra = 0, [], 0
    for _ in range(2000):
        det = f.detect(None)
        if f.dropped:
            assert len(det) == 0
            dropped += 1
            continue
        errors.append(det[:2, :2] - truth[:, :2])
        extra += len(det) - 2
    n = 2000 - dropped
    assert dropped / 2000 == pytest.approx(0.3, abs=0.03)
    assert np.std(np.array(errors)) == pytest.approx(2.0, rel=0.05)
    assert extra / n == pytest.approx(1.0, rel=0.1)


def test_a_missing_shipped_detector_is_one_clear_error(tmp_path):
    with pytest.raises(ConfigError) as e:
        load_shipped_detector(tmp_path / "no-model.onnx")
    assert "no-model.onnx" in str(e.value)
