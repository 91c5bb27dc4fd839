from __future__ import annotations

from dataclasses import replace

import numpy as np

from rebar_data.render.sensor import apply_sensor, disk_kernel, line_kernel
from rebar_data.scene.sample import SensorSample

OFF = SensorSample(
    exposure_ev=0.0,
    shot_noise=0.0,
    read_noise=0.0,
    defocus_radius_px=0.0,
    motion_blur_px=0.0,
    motion_blur_angle_deg=0.0,
    vignetting=0.0,
    jpeg_quality=0,
)


def _scene(h=64, w=80):
    rng = np.random.default_rng(0)
    img = np.full((h, w, 3), 0.15, np.float32)
    img[:, w // 2 :] = 0.35  # a vertical edge
    img[20:24, 10:14] = 0.9  # a bright dot
    return img + rng.uniform(0, 0.02, img.shape).astype(np.float32)


def _run(s, img=None, seed=0):
    return apply_sensor(_scene() if img is None else img, s, np.random.default_rng(seed)).astype(float)


def test_no_effects_is_a_monotonic_tone_curve_and_deterministic():
    img = _scene()
    out = _run(OFF, img)
    assert out.shape == (64, 80, 3)
    assert np.array_equal(out, _run(OFF, img, seed=5))  # nothing random without noise
    lin, o = img[..., 1].ravel(), out[..., 1].ravel()
    order = np.argsort(lin)
    assert np.all(np.diff(o[order]) >= 0)


def test_noise_and_determinism():
    s = replace(OFF, shot_noise=0.02, read_noise=0.01)
    a, b, c = _run(s, seed=1), _run(s, seed=1), _run(s, seed=2)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert 0.5 < np.std(a - _run(OFF)) < 8


def test_exposure_brightens():
    assert _run(replace(OFF, exposure_ev=1.0)).mean() > _run(OFF).mean() + 10


def test_vignetting_darkens_the_corners_only():
    flat = np.full((64, 80, 3), 0.2, np.float32)
    v = _run(replace(OFF, vignetting=0.4), flat)
    o = _run(OFF, flat)
    assert v[0, 0].mean() < o[0, 0].mean() - 5
    assert v[32, 40].mean() > v[0, 0].mean() + 5


def test_defocus_softens_the_edge_and_motion_blur_smears_along_its_direction():
    sharp = _run(OFF)
    soft = _run(replace(OFF, defocus_radius_px=2.0))
    grad = lambda x: np.abs(np.diff(x[..., 1], axis=1)).max()  # noqa: E731
    assert grad(soft) < 0.6 * grad(sharp)
    horiz = _run(replace(OFF, motion_blur_px=6.0, motion_blur_angle_deg=0.0))
    # the dot spreads along x, not along y
    row, col = horiz[21, 4:20, 1], horiz[14:30, 11, 1]
    assert (row > sharp[21, 30, 1] + 10).sum() > (col > sharp[21, 30, 1] + 10).sum()


def test_kernels_are_normalised():
    for k in (disk_kernel(1.7), line_kernel(5.0, 30.0)):
        assert np.isclose(k.sum(), 1.0) and (k >= 0).all()


def test_jpeg_adds_artefacts_growing_with_compression():
    base = _run(OFF)
    q90 = _run(replace(OFF, jpeg_quality=90))
    q20 = _run(replace(OFF, jpeg_quality=20))
    e90, e20 = np.abs(q90 - base).mean(), np.abs(q20 - base).mean()
    assert 0 < e90 < e20
