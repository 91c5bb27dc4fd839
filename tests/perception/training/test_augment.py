from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from rebar_data.camera import Intrinsics
from rebar_data.perception.evaluation.data import Sample
from rebar_data.perception.inference.detector import first_stage_rays
from rebar_data.perception.training.augment import (
    Source,
    apply_affine,
    crop_rays,
    distractor_gain,
    mosaic_crop,
    photometric_batch,
    random_affine,
    single_crop,
    warp,
)
from rebar_data.perception.training.config import AugmentConfig
from tests.perception.conftest import COLOUR_OFF, STILL


def _blob_image(points: np.ndarray, h: int = 120, w: int = 160, sigma: float = 2.0) -> np.ndarray:
    """Gaussian spots centred on ``points`` (COCO corner origin: pixel (i, j) is the point (j + .5, i + .5))."""
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    img = np.zeros((h, w), np.float32)
    for u, v in points:
        img += np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma**2))
    return np.repeat(np.clip(img * 255, 0, 255).astype(np.uint8)[..., None], 3, axis=2)


def _centroid(img: np.ndarray, u: float, v: float, r: int = 7) -> np.ndarray:
    a = img[..., 0].astype(float)
    i0, j0 = int(v) - r, int(u) - r
    win = a[i0 : i0 + 2 * r + 1, j0 : j0 + 2 * r + 1]
    yy, xx = np.mgrid[i0 : i0 + 2 * r + 1, j0 : j0 + 2 * r + 1] + 0.5
    return np.array([(win * xx).sum() / win.sum(), (win * yy).sum() / win.sum()])


@pytest.mark.parametrize("seed", range(4))
def test_keypoints_move_exactly_with_the_pixels(seed):
    rng = np.random.default_rng(seed)
    point = np.array([[80.3, 61.7]])
    img = _blob_image(point)
    cfg = AugmentConfig(scale=(0.8, 1.6), rotation_deg=180.0, flip_lr=0.5, flip_ud=0.5)
    crop_from_image = random_affine(rng, centre=point[0], target=np.array([48.0, 48.0]), cfg=cfg)
    out = warp(img, crop_from_image, 96, fill=0.0)
    moved = apply_affine(point, crop_from_image)[0]
    np.testing.assert_allclose(moved, [48.0, 48.0], atol=1e-9)
    assert np.linalg.norm(_centroid(out, *moved) - moved) < 0.05


def test_a_flip_maps_u_to_width_minus_u():
    cfg = AugmentConfig(scale=(1.0, 1.0), rotation_deg=0.0, flip_lr=1.0, flip_ud=0.0)
    w = 160
    m = random_affine(
        np.random.default_rng(0), centre=np.array([w / 2, 60.0]), target=np.array([w / 2, 60.0]), cfg=cfg
    )
    np.testing.assert_allclose(apply_affine(np.array([[10.25, 7.0]]), m), [[w - 10.25, 7.0]])


def test_crop_rays_are_the_source_pixels_rays():
    camera = (200.0, 210.0, 81.0, 59.0)
    shift = np.array([[1.0, 0.0, -32.0], [0.0, 1.0, -20.0]])  # crop = source window starting at (32, 20)
    rays = crop_rays(shift, 64, camera)
    full = first_stage_rays(Intrinsics(160, 120, *camera))  # output cells of 4 px
    assert rays.shape == (2, 16, 16)
    np.testing.assert_allclose(rays, full[:, 5:21, 8:24], atol=1e-6)


def test_crop_rays_follow_a_flip():
    camera = (200.0, 200.0, 80.0, 60.0)
    cfg = AugmentConfig(scale=(1.0, 1.0), rotation_deg=0.0, flip_lr=1.0, flip_ud=0.0)
    m = random_affine(
        np.random.default_rng(0), centre=np.array([80.0, 60.0]), target=np.array([32.0, 32.0]), cfg=cfg
    )
    rays = crop_rays(m, 64, camera)
    # a mirrored frame is the frame of a mirrored camera: its left still looks to the left
    assert rays[0, 3, 0] < 0 < rays[0, 3, -1]


@pytest.mark.parametrize("seed", range(3))
def test_crop_rays_are_those_of_the_camera_that_films_the_crop(seed):
    """A similarity crop is the image of a camera of focal s f, principal point where the map puts the
    source's; the crop's rays are that camera's, so the parallax of a label stays tied to them."""
    camera = (200.0, 200.0, 81.0, 59.0)
    cfg = AugmentConfig(scale=(0.7, 1.4), rotation_deg=180.0, flip_lr=0.5, flip_ud=0.5)
    m = random_affine(
        np.random.default_rng(seed), centre=np.array([70.0, 50.0]), target=np.array([32.0, 32.0]), cfg=cfg
    )
    s = np.sqrt(abs(np.linalg.det(m[:, :2])))
    c = apply_affine(np.array([camera[2:]]), m)[0]
    virtual = (s * camera[0], s * camera[1], c[0], c[1])
    np.testing.assert_allclose(
        crop_rays(m, 64, camera), first_stage_rays(Intrinsics(64, 64, *virtual)), atol=1e-5
    )


def test_single_crop_keeps_points_in_the_crop_and_on_their_spots():
    rng = np.random.default_rng(1)
    pts = rng.uniform(15, 105, (12, 2))
    src = Source(_blob_image(pts), pts, np.zeros((0, 2)), (150.0, 150.0, 80.0, 60.0))
    for _ in range(5):
        crop = single_crop(src, rng, size=64, cfg=AugmentConfig(scale=(0.9, 1.2)))
        assert crop.image.shape == (64, 64, 3) and crop.rays.shape == (2, 16, 16)
        for u, v in crop.positives:
            assert 0 <= u < 64 and 0 <= v < 64
            assert crop.image[int(v), int(u), 0] > 150


def test_a_frame_from_another_focal_length_is_cropped_at_the_models_with_the_same_draws():
    """A source's gain multiplies every crop's scale (the same random draws): two points 40 px apart land
    half as far apart in a crop with gain 0.5 as with gain 1, each on its spot; the training images give a
    frame of twice the model's focal length that gain, and one within the tolerance 1."""
    from rebar_data.perception.inference.image import TOLERANCE
    from rebar_data.perception.training.epochs import TrainingImages

    pts = np.array([[40.0, 60.0], [80.0, 60.0]])
    image = _blob_image(pts)
    spans = []
    for gain in (1.0, 0.5):
        src = Source(image, pts, np.zeros((0, 2)), (150.0, 150.0, 80.0, 60.0), gain=gain)
        crop = single_crop(src, np.random.default_rng(4), size=400, cfg=AugmentConfig(scale=(0.9, 1.1)))
        assert len(crop.positives) == 2
        assert all(crop.image[int(v), int(u), 0] > 150 for u, v in crop.positives)
        spans.append(np.linalg.norm(crop.positives[1] - crop.positives[0]))
    assert spans[1] == pytest.approx(spans[0] / 2)
    near = 525.0 * (1 + TOLERANCE / 2)
    samples = [
        Sample("a", Path("a.png"), 10, 10, np.zeros((0, 2)), np.zeros(0), camera=(f, f, 5.0, 5.0))
        for f in (1050.0, near, 525.0)
    ]
    assert TrainingImages(samples, cache=False, occluded="ignore", focal_px=525.0).gains == [
        0.5,
        1.0,
        1.0,
    ]
    assert TrainingImages(samples, cache=False, occluded="ignore").gains == [1.0] * 3


def test_mosaic_puts_every_positive_on_its_spot_and_marks_seam_points_ignored():
    rng = np.random.default_rng(2)
    sources = []
    for k in range(4):
        pts = np.random.default_rng(k).uniform(10, 110, (20, 2))
        sources.append(Source(_blob_image(pts), pts, np.zeros((0, 2)), (150.0, 150.0, 80.0, 60.0)))
    cfg = AugmentConfig(scale=(1.0, 1.3))
    n_pos = 0
    for _ in range(6):
        crop = mosaic_crop(lambda: sources[int(rng.integers(4))], rng, size=96, cfg=cfg)
        n_pos += len(crop.positives)
        for u, v in crop.positives:
            assert crop.image[int(v), int(u), 0] > 150
        assert np.isfinite(crop.rays).all() and crop.rays.shape == (2, 24, 24)
    assert n_pos > 20


def test_a_batch_gets_one_change_per_image_and_none_with_every_change_off():
    rng = np.random.default_rng(0)
    image = rng.integers(40, 200, (16, 16, 3), dtype=np.uint8)
    cfg = AugmentConfig(blur_probability=0.5, noise_probability=0.5)
    out = photometric_batch(np.stack([image] * 8), np.random.default_rng(1), cfg)
    assert out.shape == (8, 16, 16, 3) and out.dtype == np.uint8
    assert len({x.tobytes() for x in out}) == 8  # eight copies, eight different changes
    # with every change off the pixels stay as they are
    np.testing.assert_array_equal(photometric_batch(np.stack([image] * 3), rng, STILL), [image] * 3)


def test_white_balance_and_full_hue_turns_change_colour_alone():
    """Each change alone: white balance scales each channel by its own factor within its range; a full hue
    turn moves a colour's hue anywhere on the wheel, greens among them."""
    image = np.full((8, 8, 3), 100, np.uint8)
    out = photometric_batch(
        np.stack([image] * 64),
        np.random.default_rng(0),
        AugmentConfig(**{**COLOUR_OFF, "white_balance": 0.2}),
    )
    per_channel = out.reshape(64, -1, 3).mean(axis=1)
    assert per_channel.min() >= 79 and per_channel.max() <= 121
    assert np.ptp(per_channel, axis=0).min() > 20  # each channel scaled independently
    assert (np.ptp(per_channel, axis=1) > 5).mean() > 0.5  # grey turns into colour casts
    orange = np.zeros((8, 8, 3), np.uint8)
    orange[...] = (200, 100, 20)
    turned = photometric_batch(
        np.stack([orange] * 64),
        np.random.default_rng(0),
        AugmentConfig(**{**COLOUR_OFF, "hue_full_probability": 1.0}),
    )
    hue = cv2.cvtColor(turned[:, 0, :1].reshape(1, -1, 3), cv2.COLOR_RGB2HSV_FULL)[0, :, 0].astype(float)
    assert np.ptp(hue) > 180  # hues spread around the wheel (256 steps)
    greenish = ((turned[:, 0, 0, 1] > turned[:, 0, 0, 0]) & (turned[:, 0, 0, 1] > turned[:, 0, 0, 2])).sum()
    assert greenish > 5  # epoxy-like greens among them


def test_the_distractor_gain_scales_the_distractors_pixels_alone_within_its_range():
    image = np.random.default_rng(0).integers(20, 120, (30, 40, 3), dtype=np.uint8)
    mask = np.zeros((30, 40), bool)
    mask[5:15, 10:30] = True
    cfg = AugmentConfig(distractor_gain=(0.8, 1.5), distractor_gain_probability=1.0)
    rng = np.random.default_rng(1)
    ratios = []
    for _ in range(40):
        out = distractor_gain(image, mask, rng, cfg)
        np.testing.assert_array_equal(out[~mask], image[~mask])
        ratio = out[mask].astype(float).sum() / image[mask].astype(float).sum()
        assert 0.79 <= ratio <= 1.51
        ratios.append(ratio)
    assert min(ratios) < 0.95 and max(ratios) > 1.3  # darker and brighter both drawn
    # at a share of 0, or without the pixels, the image itself comes back and nothing is drawn
    off = AugmentConfig(distractor_gain=(0.8, 1.5), distractor_gain_probability=0.0)
    for cfg_off, m in ((off, mask), (cfg, None)):
        rng = np.random.default_rng(2)
        assert distractor_gain(image, m, rng, cfg_off) is image
        assert rng.uniform() == np.random.default_rng(2).uniform()
    with pytest.raises(ValueError, match="low <= high"):
        AugmentConfig(distractor_gain=(1.5, 0.8))
