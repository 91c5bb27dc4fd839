from __future__ import annotations

import numpy as np

from rebar_data.scene.config import SceneConfig
from rebar_data.scene.lighting import direction_in_frame, kelvin_to_rgb, light_specs
from rebar_data.scene.sample import sample_scene, sample_sensor


def test_same_seed_same_scene_and_fixed_columns():
    cfg = SceneConfig()
    a = sample_scene(cfg, np.random.default_rng(1))
    b = sample_scene(cfg, np.random.default_rng(1))
    assert a == b and a.record() == b.record()
    keys = set(a.record())
    for seed in range(2, 12):
        assert set(sample_scene(cfg, np.random.default_rng(seed)).record()) == keys
    assert all(k.startswith(("light_", "mat_", "surr_")) for k in keys)
    assert all(isinstance(v, float | int | str | bool) for v in a.record().values())


def test_lamp_slots_are_padded_to_the_largest_count():
    cfg = SceneConfig.model_validate({"lighting": {"lamps": {"count": [0, 3]}}})
    records = [sample_scene(cfg, np.random.default_rng(s)).record() for s in range(20)]
    assert {len(r) for r in records} == {len(records[0])}
    kinds = [r[f"light_lamp{i}_kind"] for r in records for i in range(3)]
    assert "none" in kinds and {"point", "spot", "area"} & set(kinds)


def test_every_kind_is_drawn():
    cfg = SceneConfig()
    scenes = [sample_scene(cfg, np.random.default_rng(s)) for s in range(60)]
    assert {s.ground.kind for s in scenes} == {"concrete", "soil", "plywood", "gravel"}
    assert {s.ground.shape for s in scenes} == {"plane", "follow"}
    assert {lamp.kind for s in scenes for lamp in s.lamps} == {"point", "spot", "area"}
    assert len({s.ambient.environment for s in scenes}) >= 6
    assert {s.shadows for s in scenes} == {True, False}
    assert {s.distractors.lower_layer for s in scenes} == {True, False}


def test_sensor_sample_record_and_switches():
    cfg = SceneConfig.model_validate(
        {"sensor": {"jpeg_probability": 0.0, "motion_blur_probability": 1.0, "defocus_probability": 0.0}}
    )
    s = sample_sensor(cfg, np.random.default_rng(0))
    assert s.jpeg_quality == 0 and s.defocus_radius_px == 0.0 and s.motion_blur_px >= 1.0
    rec = s.record()
    assert rec["sensor_motion_blur_px"] == s.motion_blur_px and all(k.startswith("sensor_") for k in rec)
    assert sample_sensor(cfg, np.random.default_rng(0)) == s


def test_colour_temperature():
    white = kelvin_to_rgb(6500)
    assert np.all(white > 0.9)
    warm = kelvin_to_rgb(2700)
    assert warm[0] == 1.0 and warm[0] > warm[1] > warm[2]
    cold = kelvin_to_rgb(12000)
    assert cold[2] == 1.0 and cold[0] < cold[2]


def test_lights_are_scaled_to_the_exposure_and_placed_on_the_outer_side():
    scene = sample_scene(SceneConfig(), np.random.default_rng(4))
    frame = (np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]))
    lights, ibl, scale = light_specs(scene, frame)
    on_mat = scene.ambient.illuminance_lux * scale
    for light in [scene.sun, *scene.lamps]:
        if light.kind != "none":
            to = direction_in_frame(light.azimuth_deg, light.elevation_deg, *frame[1:])
            on_mat += light.illuminance_lux * scale * max(to[2], 0.0)
    assert np.isclose(on_mat, scene.exposure_lux)
    assert ibl > 0
    for spec in lights:
        if spec.kind != "sun":
            assert spec.position[2] > 0  # above the mat
        assert spec.direction[2] < 0 or spec.kind == "point"  # shining onto it
