from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from rebar_data.config import ConfigError, validate
from rebar_data.render.depth_sensor import misregister, sense_depth, unseen_from_offset_view
from rebar_data.scene.config import DepthSensorConfig, SceneConfig
from rebar_data.scene.sample import DepthSensorSample, sample_depth_sensor

FX = 525.0
H, W = 60, 400
EDGE = 200  # first column of the foreground plane


def _sensor(model: str, **changes) -> DepthSensorSample:
    cfg = DepthSensorConfig(models={model: 1.0}, misregistration_px=(0.0, 0.0))
    return replace(sample_depth_sensor(cfg, np.random.default_rng(0)), **changes)


def _step(z_near: float, z_far: float, *, foreground_right: bool = True) -> np.ndarray:
    """Two planes: the background at z_far and, from column EDGE on (or up to it), a foreground at z_near."""
    z = np.full((H, W), z_far, np.float32)
    if foreground_right:
        z[:, EDGE:] = z_near
    else:
        z[:, :EDGE] = z_near
    return z


def _invalid_columns(depth: np.ndarray) -> np.ndarray:
    """Columns with no measurement in every row (the step scenes are the same in every row)."""
    return np.flatnonzero((depth == 0).all(axis=0))


@pytest.mark.parametrize(
    ("model", "z_far"),
    [("structured_light", 1.0), ("structured_light", 1.6), ("active_stereo", 1.0), ("active_stereo", 1.6)],
)
def test_the_shadow_band_lies_beside_the_edge_away_from_the_second_view_as_wide_as_the_disparity_jump(
    model, z_far
):
    z_near = 0.6
    s = _sensor(model, noise=0.0)
    band = FX * s.baseline_m * (1 / z_near - 1 / z_far)
    out = sense_depth(_step(z_near, z_far), s, np.random.default_rng(1), fx=FX)
    holes = _invalid_columns(out)
    margin = holes[holes < FX * s.baseline_m / z_far]  # the left margin, unseen by a second camera
    assert (len(margin) > 0) == (model == "active_stereo")  # a projector's wider field lights it
    shadow = np.setdiff1d(holes, margin)
    assert abs(len(shadow) - band) <= 1, (len(shadow), band)
    assert shadow.max() == EDGE - 1 and np.all(np.diff(shadow) == 1)  # one band, ending at the edge
    assert (out[:, EDGE:] > 0).all()  # the foreground itself is measured
    # a foreground on the left casts no band beside its right edge
    out = sense_depth(_step(z_near, z_far, foreground_right=False), s, np.random.default_rng(1), fx=FX)
    assert (out[:, EDGE - 10 : EDGE + 10] > 0).all()


def test_a_second_view_on_the_other_side_puts_the_band_on_the_other_side():
    z = _step(0.6, 1.0, foreground_right=False)
    band = FX * 0.075 * (1 / 0.6 - 1 / 1.0)
    unseen = unseen_from_offset_view(z, FX, -0.075)
    cols = np.flatnonzero(unseen.all(axis=0))
    cols = cols[cols < W - FX * 0.075 / 1.0 - 1]  # less the right margin
    assert cols.min() == EDGE and abs(len(cols) - band) <= 1


def test_a_bar_narrower_than_the_matching_window_leaves_a_hole_in_active_stereo_and_a_wider_one_stays():
    s = _sensor("active_stereo", noise=0.0, window_px=7)
    z = np.full((H, W), 1.0, np.float32)
    z[:, 250:254] = 0.9  # 4 px: narrower than the window
    z[:, 300:320] = 0.9  # 20 px
    out = sense_depth(z, s, np.random.default_rng(2), fx=FX)
    assert (out[:, 250:254] == 0).all()
    assert np.allclose(out[5:-5, 305:320], 0.9, atol=1e-3)


def test_structured_light_reads_a_sub_window_bar_as_the_surface_behind_it():
    s = _sensor("structured_light", noise=0.0, window_px=9)
    z = np.full((H, W), 1.0, np.float32)
    z[:, 250:254] = 0.95
    out = sense_depth(z, s, np.random.default_rng(2), fx=FX)
    assert np.allclose(out[:, 250:254], 1.0, atol=0.01)


def test_time_of_flight_flying_pixels_lie_between_the_foreground_and_the_background():
    s = _sensor("time_of_flight", noise=0.0, noise_per_m=0.0, flying_pixel_probability=1.0)
    z_near, z_far = 0.7, 1.2
    out = sense_depth(_step(z_near, z_far), s, np.random.default_rng(3), fx=FX)
    edge = out[:, EDGE - 1 : EDGE + 1]
    assert (edge >= z_near).all() and (edge <= z_far).all()
    between = (edge > z_near + 0.01) & (edge < z_far - 0.01)
    assert between.mean() > 0.8  # mixed, not snapped to either side
    assert (out[:, : EDGE - 1] == z_far).all() and (out[:, EDGE + 1 :] == z_near).all()  # no band, no holes


def test_structured_light_quantises_disparity_in_eighth_pixels():
    s = _sensor("structured_light", noise=0.0, window_px=1)
    z = np.tile(np.linspace(1.0, 1.3, W, dtype=np.float32), (H, 1))
    out = sense_depth(z, s, np.random.default_rng(4), fx=FX)
    fb = s.focal_px * s.baseline_m
    eighths = fb / out[out > 0] * 8
    assert np.allclose(eighths, np.round(eighths), atol=1e-3)
    levels = np.unique(np.round(eighths).astype(int))
    assert np.all(np.diff(levels) == 1)  # every step met, none skipped
    # the depth step at 1.2 m is z^2 / (f b) / 8
    near = np.sort(np.unique(np.round(out[(out > 1.15) & (out < 1.25)], 5)))
    assert np.allclose(np.diff(near), 1.2**2 / fb / 8, rtol=0.1)


def test_exact_is_the_ray_cast_and_the_same_seed_gives_the_same_depth():
    z = np.random.default_rng(5).uniform(0.3, 3.0, (H, W)).astype(np.float32)
    z[:5] = 0.0
    assert np.array_equal(sense_depth(z, _sensor("exact"), np.random.default_rng(0), fx=FX), z)
    for model in ("structured_light", "active_stereo", "time_of_flight"):
        s = _sensor(model)
        a = sense_depth(z, s, np.random.default_rng(9), fx=FX)
        b = sense_depth(z, s, np.random.default_rng(9), fx=FX)
        assert np.array_equal(a, b) and not np.array_equal(a, z)


def test_misregistration_moves_the_depth_image_by_the_drawn_offset():
    cfg = DepthSensorConfig(models={"exact": 1.0}, misregistration_px=(1.0, 2.0))
    z = np.random.default_rng(6).uniform(0.5, 2.0, (H, W)).astype(np.float32)
    for seed in range(8):
        s = sample_depth_sensor(cfg, np.random.default_rng(seed))
        assert 1.0 <= np.hypot(s.shift_x_px, s.shift_y_px) <= 2.0
        dx, dy = int(np.rint(s.shift_x_px)), int(np.rint(s.shift_y_px))
        out = sense_depth(z, s, np.random.default_rng(0), fx=FX)
        assert np.array_equal(out[5 + dy : H - 5 + dy, 5 + dx : W - 5 + dx], z[5 : H - 5, 5 : W - 5])
    assert misregister(z, 2.0, 0.0)[:, :2].max() == 0.0  # uncovered: no measurement


def test_range_limits_read_as_no_measurement():
    s = _sensor("active_stereo", noise=0.0)
    z = np.full((H, W), 0.1, np.float32)  # nearer than f b / 126 px = 0.18 m
    assert (sense_depth(z, s, np.random.default_rng(0), fx=FX) == 0).all()


def test_the_depth_sensor_config_names_the_bad_field():
    with pytest.raises(ConfigError, match=r"depth_sensor\.models.*'sonar'.*accepted: exact"):
        validate(SceneConfig, {"depth_sensor": {"models": {"sonar": 1.0}}}, "p.yaml")
    with pytest.raises(ConfigError, match=r"window_px.*odd"):
        validate(SceneConfig, {"depth_sensor": {"active_stereo": {"window_px": [6, 8]}}}, "p.yaml")
