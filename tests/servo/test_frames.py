"""The renderer's frames for the loop: a suite's ``scene`` section decides what is drawn."""

from __future__ import annotations

import numpy as np

from rebar_data.scene.config import SceneConfig
from rebar_data.servo.config import StartPose, SuiteConfig

from .conftest import suite_dict


def _depths(servo_ctx, lower_layer_probability: float) -> tuple[np.ndarray, object]:
    from rebar_data.servo.frames import RendererFrames

    scene = SceneConfig.model_validate(
        {
            "surroundings": {"distractors": {"lower_layer_probability": lower_layer_probability}},
            "sensor": {"motion_blur_probability": 1.0, "defocus_probability": 1.0},
        }
    )
    frames = RendererFrames(servo_ctx.rm, servo_ctx.camera, np.random.default_rng(5), scene=scene)
    try:
        pose = servo_ctx.world.camera_pose_for(StartPose(look_at_m=(0.03, -0.02), standoff_m=0.6))
        frame = frames.render(pose, np.random.default_rng(0))
        return frame.depth_m, frames._scene_cfg
    finally:
        frames.close()


def test_the_suite_scene_section_decides_the_lower_mat(servo_ctx):
    with_mat, cfg = _depths(servo_ctx, 1.0)
    without, _ = _depths(servo_ctx, 0.0)
    # The loop's camera never blurs at random, whatever the scene section says.
    assert cfg.sensor.motion_blur_probability == 0.0 and cfg.sensor.defocus_probability == 0.0
    # The top mat is about 0.6 m away; the lower mat lies 0.1-0.2 m beneath it, the ground further.
    band = lambda d: np.mean((d > 0.68) & (d < 0.82))  # noqa: E731
    assert band(with_mat) > 0.02, band(with_mat)
    assert band(without) < 0.2 * band(with_mat), (band(without), band(with_mat))


def test_a_suite_takes_a_scene_section():
    suite = SuiteConfig.model_validate(
        suite_dict(scene={"surroundings": {"distractors": {"lower_layer_probability": 0.0}}})
    )
    assert suite.scene.surroundings.distractors.lower_layer_probability == 0.0
    assert suite.scene.lighting == SceneConfig().lighting
