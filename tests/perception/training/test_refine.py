from __future__ import annotations

import json
import shutil

import numpy as np
import onnx
import pytest
import torch

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import load_split, read_image
from rebar_data.perception.evaluation.evaluate import first_stage_only
from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.detector import Detector, log_probability, shifted_score
from rebar_data.perception.inference.refine import Refiner, patches, shrunk, shrunk_around
from rebar_data.perception.networks import eager
from rebar_data.perception.networks.files import export_onnx, quantize_onnx
from rebar_data.perception.training.config import AugmentConfig, RefineConfig
from rebar_data.perception.training.refine import (
    build,
    calibration_patches,
    first_stage_detections,
    negatives_in,
    train_refiner,
)
from rebar_data.perception.training.refine_data import (
    patch_batches,
    patch_geometry,
    training_patch,
)
from tests.perception.conftest import STILL, TINY_TRAIN, refined


def verified_score(score: np.ndarray, verify_logit: np.ndarray, *, power: float = 1.0) -> np.ndarray:
    """sigmoid(logit(score) + power * log sigmoid(``verify_logit``)): a score the verification lowered."""
    return shifted_score(score, power * log_probability(verify_logit))


def _blob(h: int, w: int, centre: np.ndarray, sigma: float = 2.0) -> np.ndarray:
    """A Gaussian spot at ``centre`` (COCO corner origin: pixel (i, j) is the point (j + 0.5, i + 0.5))."""
    y, x = np.mgrid[0:h, 0:w] + 0.5
    g = np.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2 * sigma**2))
    return np.repeat((255 * g).astype(np.uint8)[..., None], 3, axis=2)


def _centroid(img: np.ndarray) -> np.ndarray:
    g = img[..., 0].astype(float)
    y, x = np.mgrid[0 : g.shape[0], 0 : g.shape[1]] + 0.5
    return np.array([(g * x).sum(), (g * y).sum()]) / g.sum()


def _centroid_offsets(x: np.ndarray) -> np.ndarray:
    """(N, 2) each patch's spot centroid (channel 0) from the patch centre: what a stand-in network reads."""
    size = x.shape[1]
    g = x[..., 0].astype(float)
    y, xx = np.mgrid[0:size, 0:size] + 0.5 - size / 2
    return (
        np.stack([(g * xx).sum(axis=(1, 2)), (g * y).sum(axis=(1, 2))], axis=1) / g.sum(axis=(1, 2))[:, None]
    )


def _spread(img: np.ndarray) -> float:
    """The RMS distance of a spot's brightness from its centroid (pixels)."""
    g = img[..., 0].astype(float)
    y, x = np.mgrid[0 : g.shape[0], 0 : g.shape[1]] + 0.5
    cx, cy = _centroid(img)
    return float(np.sqrt((g * ((x - cx) ** 2 + (y - cy) ** 2)).sum() / g.sum()))


def test_a_patch_is_centred_on_the_point_in_coco_pixels():
    ramp = np.repeat(np.tile(np.arange(64, dtype=np.uint8), (48, 1))[..., None], 3, axis=2)
    p, corners = patches(ramp, np.array([[10.0, 20.0], [30.6, 5.0], [1.2, 47.9]]), 4)
    assert p.shape == (3, 4, 4, 3)
    # the point (10, 20) is the corner between pixels 9 and 10: the 4 px patch spans pixels 8 to 11
    np.testing.assert_array_equal(p[0, 0, :, 0], [8, 9, 10, 11])
    np.testing.assert_array_equal(corners, [[10, 20], [31, 5], [1, 48]])  # the nearest pixel corners
    np.testing.assert_array_equal(p[1, 0, :, 0], [29, 30, 31, 32])
    np.testing.assert_array_equal(p[2, 0, :, 0], [0, 0, 1, 2])  # mirrored beyond the border
    point = np.array([23.3, 17.8])
    spot, corner = patches(_blob(48, 64, point), point[None], 24)
    np.testing.assert_allclose(_centroid(spot[0]), 12 + point - corner[0], atol=0.05)


def test_turned_views_of_a_patch_are_turned_back_to_one_answer():
    """A stand-in network that reads a spot's centroid (offset from the patch centre) and, as its logit,
    how far right the spot lies: every view, turned back, puts the spot where it is, and the logit is the
    plain view's alone."""
    size = 24
    point = np.array([40.3, 27.8])
    img = _blob(64, 80, point, sigma=1.5)

    def run(x: np.ndarray) -> np.ndarray:
        c = _centroid_offsets(x)
        return np.concatenate([c, c[:, :1]], axis=1).astype(np.float32)

    start = np.array([[38.2, 29.1]])
    du = (point - np.floor(start[0] + 0.5))[0]  # the spot's column offset from the patch centre
    for views in (1, 2, 4, 8):
        r = Refiner(run, patch_px=size, iterations=1, verifies=True, views=views)
        uv, logit = refined(r, img, start)
        np.testing.assert_allclose(uv[0], point, atol=0.05)
        # the flipped views see -du or the row offset there: averaged in, the logit would not be du
        assert logit[0] == pytest.approx(du, abs=0.05)


def test_a_later_pass_moves_the_point_its_step_of_the_way():
    """A stand-in network that always reads the crossing 1 px right of the patch's corner, and as its logit
    how many times it has been run: the first pass moves the point all the way, each later one ``step`` of
    the way to where it then reads the crossing, and the logit is the first pass's."""
    calls = []

    def run(x: np.ndarray) -> np.ndarray:
        calls.append(len(x))
        out = np.zeros((len(x), 3), np.float32)
        out[:, 0], out[:, 2] = 1.0, len(calls)
        return out

    img = np.zeros((40, 50, 3), np.uint8)
    start = np.array([[20.0, 15.0]])
    for iterations, step, want in ((1, 0.5, 21.0), (2, 1.0, 22.0), (2, 0.5, 21.5), (3, 0.5, 22.25)):
        calls.clear()
        r = Refiner(run, patch_px=16, iterations=iterations, verifies=True, step=step)
        uv, logit = refined(r, img, start)
        # the second pass cuts its patch at the corner nearest 21.0 (21), reads 22 and goes half way; the
        # third at the corner nearest 21.5 (22), reads 23 and goes half way from 21.5 (22.25)
        assert uv[0, 0] == pytest.approx(want) and uv[0, 1] == pytest.approx(15.0)
        assert len(calls) == iterations and logit[0] == 1.0


def test_the_first_pass_reads_its_own_number_of_views():
    """``first_pass_views`` views in the first pass, ``views`` in each later one (one batch each); without
    it every pass reads ``views``; a count that is no symmetry group's size is refused by name."""
    calls = []

    def run(x: np.ndarray) -> np.ndarray:
        calls.append(len(x))
        return np.zeros((len(x), 3), np.float32)

    img = np.zeros((40, 50, 3), np.uint8)
    start = np.array([[20.0, 15.0], [30.0, 22.0]])
    for first, want in ((1, [2, 4, 4]), (4, [8, 4, 4]), (None, [4, 4, 4])):
        calls.clear()
        refined(
            Refiner(run, patch_px=16, iterations=3, verifies=True, views=2, first_pass_views=first),
            img,
            start,
        )
        assert calls == want
    # ``keep`` says which points the later passes go on moving: only those are read again
    calls.clear()
    r = Refiner(run, patch_px=16, iterations=3, verifies=True, views=1)
    kept = refined(r, img, start, keep=lambda logit: np.array([False, True]))[0]
    assert calls == [2, 1, 1]
    np.testing.assert_array_equal(kept, refined(r, img, start)[0])  # the stand-in never moves them


def test_a_refiner_with_sizes_reads_a_large_crossing_again_from_the_shrunk_image():
    """A stand-in network that reads a spot's centroid and says the crossing's box is ``box`` px: the later
    pass reads the patch at full resolution, at 0.75 or at 0.5 as the box exceeds neither, the first or
    the second of ``shrink_above_px``, and places the spot where it is at every resolution."""
    size, point = 24, np.array([40.3, 27.8])
    img = _blob(64, 80, point, sigma=3.0)
    seen: list[float] = []

    def stand_in(box: float):
        def run(x: np.ndarray) -> np.ndarray:
            c = _centroid_offsets(x)
            seen.extend(_spread(p) for p in x)
            return np.concatenate(
                [c, np.zeros((len(x), 1)), np.full((len(x), 1), np.log(box / size))], 1
            ).astype(np.float32)

        return run

    start = np.array([[38.2, 29.1]])
    for box, shrink in ((40.0, 1.0), (70.0, 0.75), (120.0, 0.5)):
        seen.clear()
        r = Refiner(
            stand_in(box), patch_px=size, iterations=2, verifies=True, sizes=True, shrink_above_px=(50, 90)
        )
        uv, _ = refined(r, img, start)
        np.testing.assert_allclose(uv[0], point, atol=0.1)
        # the spot's spread in the second pass's patch: shrunk with the image
        assert seen[1] / seen[0] == pytest.approx(shrink, rel=0.08)
    without = Refiner(stand_in(120.0), patch_px=size, iterations=2, verifies=True, sizes=True)
    seen.clear()
    refined(without, img, start)
    assert seen[1] == pytest.approx(seen[0], rel=0.02)  # no shrink_above_px: every pass at full resolution


def test_the_later_pass_reads_every_resolution_in_one_network_call():
    """Three spots whose first pass calls for the three resolutions: the later pass cuts each from its own
    (shrunk) image and sends the three patches through the network in one call, each placed on its spot."""
    size = 24
    points = np.array([[30.3, 30.8], [90.6, 34.2], [150.2, 29.7]])
    img = np.max([_blob(64, 184, p, sigma=3.0) for p in points], axis=0)
    calls: list[int] = []
    boxes = iter([40.0, 70.0, 120.0])  # the first pass's box for each spot, in turn

    def run(x: np.ndarray) -> np.ndarray:
        calls.append(len(x))
        box = [next(boxes) for _ in x] if len(calls) == 1 else [40.0] * len(x)
        return np.concatenate(
            [_centroid_offsets(x), np.zeros((len(x), 1)), np.log(np.array(box)[:, None] / size)], 1
        ).astype(np.float32)

    r = Refiner(run, patch_px=size, iterations=2, verifies=True, sizes=True, shrink_above_px=(50, 90))
    uv, _ = refined(r, img, points + [[-1.7, 1.2], [1.4, -1.1], [-0.9, -1.3]])
    assert calls == [3, 3]
    np.testing.assert_allclose(uv, points, atol=0.15)


@pytest.mark.parametrize("height, width", [(480, 640), (484, 644), (481, 641), (30, 36)])
@pytest.mark.parametrize("scale", [4 / 3, 2.0])
def test_shrinking_only_around_the_points_cuts_the_patches_the_whole_shrunk_image_gives(height, width, scale):
    """The later pass's shrunk patches, from only the regions they read (:func:`shrunk_around`): pixel for
    pixel those of the whole image shrunk, for points inside, at and beyond the frame's edges, at frame
    sizes the factor divides into whole blocks and sizes where it falls back to the whole image."""
    rng = np.random.default_rng(int(height * scale))
    img = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    points = np.concatenate(
        [
            rng.uniform([-6, -6], [width + 6, height + 6], (25, 2)),
            [[0.0, 0.0], [width, height], [width / 2, 1.2]],
        ]
    )
    whole, whole_factors = shrunk(img, scale)
    around, factors = shrunk_around(img, points, scale, 32)
    np.testing.assert_array_equal(factors, whole_factors)
    assert around.shape == whole.shape
    want, want_corners = patches(whole, points * factors, 32, border="mask")
    got, corners = patches(around, points * factors, 32, border="mask")
    np.testing.assert_array_equal(corners, want_corners)
    np.testing.assert_array_equal(got, want)
    if (height, width, scale) == (480, 640, 4 / 3):  # a few points: most of the shrunk frame left undone
        few, _ = shrunk_around(img, points[:3], scale, 32)
        assert (few == 0).all(axis=2).mean() > 0.5
    empty, _ = shrunk_around(img, np.zeros((0, 2)), scale, 32)
    assert empty.shape == whole.shape


def test_the_size_target_is_the_box_as_the_patch_shows_it(drawn_dataset):
    samples = load_split(drawn_dataset, "train")
    negatives = [s.visible[:1] + 9.0 for s in samples]
    cfg = RefineConfig(patch_px=16, epochs=1, batch_size=64, size=True, scale=(1.5, 1.5), border_fraction=0.0)
    # turned and flipped at random; scaled 1.5 times (the patches' own scale range)
    x, y, labelled, _ = next(patch_batches(samples, negatives, cfg, STILL, seed=1, first=1))
    assert y.shape == (64, 3) and labelled.any()
    boxes = np.concatenate([s.box_size_px for s in samples])
    got = np.exp(y[labelled, 2].numpy()) * 16 / 1.5  # back to the image's pixels
    assert (np.abs(got[:, None] - boxes[None]).min(axis=1) < 1e-3 * got).all()  # each one of the boxes
    with pytest.raises(ValueError, match="needs verify"):
        RefineConfig(size=True, verify=False)
    with pytest.raises(ValueError, match="smaller first"):
        RefineConfig(shrink_above_px=(90, 50))


def test_a_training_patch_moves_its_offset_with_the_pixels():
    crossing = np.array([41.7, 30.2])
    image = _blob(64, 80, crossing)
    cfg = RefineConfig(patch_px=32, jitter_px=2.0, jitter_uniform_px=4.0, border_fraction=0.0)
    rng = np.random.default_rng(3)
    offsets = []
    for _ in range(20):  # random errors, turns, flips and scales: the spot is where the offset says
        x, y, _ = training_patch(image, crossing, rng, cfg, patch_geometry(cfg, STILL))
        np.testing.assert_allclose(_centroid(x), 16 + y, atol=0.15)
        offsets.append(y)
    assert np.std(offsets) > 0.5  # the centre really was off the crossing


@pytest.mark.parametrize("at", [(40.0, 30.0), (3.0, 30.0), (77.5, 62.0)])
def test_a_training_patch_scales_the_distractors_as_the_whole_frame_scaled(at):
    """Only the pixels a patch reads are scaled: the patch is the one cut from the
    whole frame with its distractor pixels scaled, inside the frame and across its border."""
    rng = np.random.default_rng(0)
    image = rng.integers(0, 200, (64, 80, 3), dtype=np.uint8)
    mask = rng.uniform(size=(64, 80)) < 0.4
    gain = 1.3
    geometry = STILL.model_copy(
        update={"distractor_gain": (gain, gain), "distractor_gain_probability": 1.0, "scale": (0.8, 1.25)}
    )
    cfg = RefineConfig(patch_px=16, border_fraction=0.0)
    whole = image.copy()
    whole[mask] = np.clip(whole[mask] * np.float32(gain), 0, 255).astype(np.uint8)
    for seed in range(6):  # random errors, turns, flips and scales
        x, y, s = training_patch(
            image, np.array(at), np.random.default_rng(seed), cfg, geometry, distractors=mask
        )
        plain = np.random.default_rng(seed)
        plain.uniform(size=2)  # the two draws the gain took
        ref, y_ref, s_ref = training_patch(whole, np.array(at), plain, cfg, geometry)
        np.testing.assert_allclose(y, y_ref)
        assert s == s_ref
        assert np.abs(x.astype(int) - ref.astype(int)).max() <= 1


def test_a_masked_patch_shows_where_the_frame_ends():
    image = np.random.default_rng(0).integers(0, 256, (40, 50, 3), dtype=np.uint8)
    points = np.array([[20.0, 20.0], [1.2, 10.0], [49.6, 39.7]])
    mirrored, corners = patches(image, points, 8)
    masked, masked_corners = patches(image, points, 8, border="mask")
    assert masked.shape == (3, 8, 8, 4) and masked.dtype == np.uint8
    np.testing.assert_array_equal(masked_corners, corners)
    # inside the frame: the same pixels, every one marked as on the image
    np.testing.assert_array_equal(masked[0, ..., :3], mirrored[0])
    assert (masked[0, ..., 3] == 255).all()
    # corner (1, 10): the patch spans columns -3 to 4 and rows 6 to 13; three columns lie beyond the border
    assert (masked[1, :, :3] == 0).all()  # colour and mask
    assert (masked[1, :, 3:, 3] == 255).all()
    np.testing.assert_array_equal(masked[1, :, 3:, :3], image[6:14, 0:5])
    assert not (mirrored[1, :, :3] == 0).all()  # mirrored, they show the image again
    # corner (50, 40), the image's corner: a quarter of the patch is on the image
    assert (masked[2, :4, :4, 3] == 255).all() and int(masked[2, ..., 3].sum()) == 16 * 255
    with pytest.raises(ConfigError, match="accepted: one of mirror, mask"):
        patches(image, points, 8, border="zero")


def test_a_training_patch_sees_the_frame_end_as_inference_does():
    crossing = np.array([3.0, 30.0])  # 3 px inside the left border, on the pixel grid
    image = _blob(64, 80, crossing)
    plain = STILL.model_copy(update={"rotation_deg": 0.0, "flip_lr": 0.0, "flip_ud": 0.0})
    cfg = RefineConfig(
        patch_px=16, jitter_px=0.0, jitter_uniform_fraction=0.0, scale=(1.0, 1.0), border_fraction=0.0
    )
    x, y, _ = training_patch(image, crossing, np.random.default_rng(0), cfg, patch_geometry(cfg, plain))
    cut, _ = patches(image, crossing[None], 16, border="mask")
    np.testing.assert_allclose(y, 0.0, atol=1e-9)
    assert (cut[0, :, :5, 3] == 0).all() and (cut[0, :, 5:, 3] == 255).all()
    np.testing.assert_array_equal(x, cut[0])


def test_a_training_patch_gets_a_border_of_its_own_near_its_crossing():
    crossing = np.array([41.7, 30.2])  # far from the image's border
    image = _blob(64, 80, crossing)
    cfg = RefineConfig(patch_px=32, border_fraction=1.0, border_reach_px=6.0)
    rng = np.random.default_rng(5)
    axes = set()
    for _ in range(40):
        x, y, _ = training_patch(image, crossing, rng, cfg, patch_geometry(cfg, STILL))
        beyond = x[..., 3] == 0
        assert beyond.any() and (x[beyond, :3] == 0).all()
        assert not beyond[15:17, 15:17].all()  # the patch centre (a point inside the frame) is on the image
        point = 16 + y  # the crossing, whose offset the border leaves alone
        for axis, line in ((0, beyond.all(axis=0)), (1, beyond.all(axis=1))):
            if line.any():  # a straight edge along this axis: every pixel beyond it is off the image
                off = np.nonzero(line)[0] + 0.5
                assert beyond.sum() == line.sum() * 32
                assert np.abs(off - point[axis]).min() <= cfg.border_reach_px + 1.0
                axes.add(axis)
    assert axes == {0, 1}
    # the border leaves the offset as it is, also for a crossing beyond it: the refiner learns to place it
    cfg_none = cfg.model_copy(update={"border_fraction": 0.0})
    x, y, _ = training_patch(image, crossing, np.random.default_rng(5), cfg, patch_geometry(cfg, STILL))
    x0, y0, _ = training_patch(
        image, crossing, np.random.default_rng(5), cfg_none, patch_geometry(cfg, STILL)
    )
    np.testing.assert_array_equal(y, y0)
    assert (x0[..., 3] == 255).all() and (x[..., 3] == 0).any()


def test_a_crossing_beyond_its_patch_border_is_placed_but_not_called_a_crossing(drawn_dataset):
    samples = load_split(drawn_dataset, "train")
    negatives = [s.visible[:2] + 7.0 for s in samples]
    cfg = RefineConfig(patch_px=16, epochs=1, batch_size=256, border_fraction=1.0, border_reach_px=6.0)
    x, y, labelled, crossing = next(patch_batches(samples, negatives, cfg, STILL, seed=1, first=1))
    assert x.shape[3] == 4
    assert not crossing[~labelled].any()  # negatives stay negatives
    # a labelled crossing is a crossing to the verification where the patch shows it, not beyond its border
    j, i = np.clip(np.floor(8 + y.numpy()[:, :2]).astype(int), 0, 15).T
    shown = x.numpy()[np.arange(len(x)), i, j, 3] == 255
    np.testing.assert_array_equal(crossing.numpy(), labelled.numpy() & shown)
    beyond = labelled & ~crossing
    assert (
        0.1 < float(beyond.sum()) / float(labelled.sum()) < 0.9
    )  # within 6 px of its own edge: many are beyond


def test_patch_batches_cover_every_key_once_an_epoch_and_resume_where_they_stopped(drawn_dataset):
    samples = load_split(drawn_dataset, "train")
    negatives = [s.visible[:2] + 7.0 for s in samples]
    cfg = RefineConfig(patch_px=16, epochs=2, batch_size=64)
    run = list(patch_batches(samples, negatives, cfg, AugmentConfig(), seed=4, first=1))
    steps = -(-sum(len(s.visible) + len(n) for s, n in zip(samples, negatives, strict=True)) // 64)
    assert len(run) == 2 * steps and run[0][0].shape == (64, 16, 16, 4) and run[0][0].dtype == torch.uint8
    # each epoch holds every crossing once and every negative once
    labels = torch.cat([b[2] for b in run[:steps]])
    assert int(labels.sum()) == sum(len(s.visible) for s in samples)
    assert int((~labels).sum()) == sum(len(n) for n in negatives)
    # epoch 2 alone, as after a resume, is epoch 2 of the whole run, and not a repeat of epoch 1
    resumed = list(patch_batches(samples, negatives, cfg, AugmentConfig(), seed=4, first=2))
    for a, b in zip(resumed, run[steps:], strict=True):
        for x, y in zip(a, b, strict=True):
            torch.testing.assert_close(x, y)
    assert not torch.equal(run[0][0], run[steps][0])


def test_the_refiner_learns_to_move_points_onto_crossings(drawn_dataset, tmp_path):
    samples = load_split(drawn_dataset, "train")
    cfg = RefineConfig(
        patch_px=16, widths=(8, 8, 16, 16), hidden=16, epochs=6, batch_size=32, lr=3e-3, threads=1
    )
    torch.manual_seed(0)
    net, history = train_refiner(samples, tmp_path, cfg, STILL, seed=0)
    assert len(history) == 6 and (tmp_path / "refine_last.pt").is_file()
    assert history[-1]["loss"] < 0.7 * history[0]["loss"]
    # points 1.5 px off the crossings of images it never saw come closer
    test = load_split(drawn_dataset, "test")
    rng = np.random.default_rng(0)
    before, after = [], []
    refiner = eager.refiner(net)
    for s in test:
        start = s.visible + rng.normal(0, 1.5, s.visible.shape)
        moved = refined(refiner, read_image(s.path), start)[0]
        before += list(np.linalg.norm(start - s.visible, axis=1))
        after += list(np.linalg.norm(moved - s.visible, axis=1))
    assert np.median(after) < 0.8 * np.median(before)
    # a finished stage is kept, not retrained, also when only the exported file's settings change
    for same in (cfg, cfg.model_copy(update={"quantize": "none", "calibration_patches": 64})):
        again, history_again = train_refiner(samples, tmp_path, same, STILL, seed=0)
        assert history_again == history
        torch.testing.assert_close(again.state_dict(), net.state_dict())
    # the int8 file moves the points closer as the float network does (the shipped network's int8 file
    # is within 0.03 px of its float one in median; this tiny network's, within about 0.6 px)
    calibration = calibration_patches(samples, cfg.model_copy(update={"calibration_patches": 256}), seed=0)
    assert calibration.shape == (256, 16, 16, 4) and calibration.dtype == np.uint8  # RGB and the mask
    int8 = quantize_onnx(export_onnx(net, tmp_path / "f.onnx"), tmp_path / "q.onnx", calibration)
    assert any(n.op_type == "QLinearConv" for n in onnx.load(int8).graph.node)
    quantized = model_file.read_refiner(int8, threads=1)
    rng = np.random.default_rng(0)
    after_int8 = []
    for s in test:
        start = s.visible + rng.normal(0, 1.5, s.visible.shape)
        moved = refined(quantized, read_image(s.path), start)[0]
        after_int8 += list(np.linalg.norm(moved - s.visible, axis=1))
    assert np.median(after_int8) < 0.8 * np.median(before), (np.median(after_int8), np.median(before))
    assert np.median(after_int8) < np.median(after) + 0.3, (np.median(after_int8), np.median(after))


def test_onnx_refiner_gives_what_pytorch_gives(tmp_path):
    torch.manual_seed(1)
    cfg = RefineConfig(patch_px=16, widths=(4, 4, 8, 8), hidden=8)
    net = build(cfg).eval()
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
    image = np.random.default_rng(0).integers(0, 256, (40, 50, 3), dtype=np.uint8)
    points = np.array([[10.0, 12.0], [25.5, 30.25], [0.5, 39.0]])
    path = export_onnx(net, tmp_path / "r.onnx")
    onnx_refiner = model_file.read_refiner(path, threads=1)
    assert onnx_refiner.patch_px == 16
    np.testing.assert_allclose(
        refined(onnx_refiner, image, points)[0], refined(eager.refiner(net), image, points)[0], atol=1e-4
    )


def test_a_trained_run_ships_both_stages_and_says_which_file_is_missing(trained_run, drawn_dataset, tmp_path):
    out = trained_run.out_dir
    assert (out / "best.refine.onnx").is_file() and (out / "best.refine.pt").is_file()
    det = Detector.load(out)
    assert det.refiner is not None and det.meta["refiner"]["patch_px"] == TINY_TRAIN["refine"]["patch_px"]
    assert det.meta["refiner"]["quantize"] == "later" and det.refiner.int8_run is not None
    assert any(n.op_type == "QLinearConv" for n in onnx.load(out / "best.refine.int8.onnx").graph.node)
    results = json.loads((out / "results.json").read_text())
    assert "test" in results["results_first_stage"] and results["refiner_parameters"] > 0
    assert det.meta["refiner"]["verify"] and det.refiner.verifies  # the default: it verifies too
    assert det.verify_power == det.meta["refiner"]["verify_power"] == RefineConfig().verify_power
    assert results["refine_history"][-1]["verify_positives_right"] > 0.5
    rgb = read_image(load_split(drawn_dataset, "test")[0].path)
    both = det.detect(rgb, threshold=0.01)
    with first_stage_only(det):
        first = det.detect(rgb, threshold=0.01)
    # the same detections, moved, their scores lowered by the verification and cut at the threshold
    uv, logit = refined(det.refiner, rgb, first[:, :2])
    expected = np.c_[uv, verified_score(first[:, 2], logit, power=det.verify_power)]
    expected = expected[expected[:, 2] >= 0.01]
    np.testing.assert_allclose(both, expected[np.argsort(-expected[:, 2], kind="stable")])
    det.refiner = None
    assert Detector.load(out / "best.pt").refiner is not None
    lone = tmp_path / "lone"
    lone.mkdir()
    shutil.copy(out / "best.onnx", lone / "best.onnx")
    with pytest.raises(ConfigError, match="best.refine.onnx is missing"):
        Detector.load(lone / "best.onnx")
    (lone / "best.refine.onnx").write_bytes((out / "best.refine.onnx").read_bytes()[:-1] + b"\0")
    with pytest.raises(ConfigError, match="SHA-256"):
        Detector.load(lone / "best.onnx")


def test_a_second_stage_file_that_does_not_fit_its_settings_is_named_and_retrained(drawn_dataset, tmp_path):
    from rebar_data.perception.training.refine import load, save

    small = RefineConfig(patch_px=16, widths=(4, 4, 8, 8), hidden=8, epochs=1, batch_size=64, threads=1)
    other = small.model_copy(update={"widths": (4, 8, 8, 8)})
    save(tmp_path / "refine_last.pt", build(other), small, optimizer={}, history=[])
    with pytest.raises(ConfigError, match="do not fit"):
        load(tmp_path / "refine_last.pt")
    samples = load_split(drawn_dataset, "train")
    net, history = train_refiner(samples, tmp_path, small, STILL, seed=0)  # trains afresh, no error
    assert len(history) == 1 and load(tmp_path / "refine_last.pt")[1] == small
    # a file from before verification (no such setting, two outputs) loads as a refiner that does not verify
    old = small.model_copy(update={"verify": False, "size": False})
    payload = {**torch.load(tmp_path / "refine_last.pt", weights_only=False)}
    payload["refine_config"] = {
        k: v for k, v in old.model_dump(mode="json").items() if k not in ("verify", "size")
    }
    payload["state_dict"] = build(old).state_dict()
    torch.save(payload, tmp_path / "old.pt")
    loaded, cfg, _ = load(tmp_path / "old.pt")
    assert not cfg.verify and not loaded.verify and not cfg.size and not loaded.size


def test_verification_only_lowers_a_score_and_keeps_the_score_bias_a_shift():
    score = np.array([0.3, 0.5, 0.9, 0.999])
    sure = verified_score(score, np.full(4, 30.0))  # the second stage is sure of a crossing: unchanged
    np.testing.assert_allclose(sure, score, rtol=1e-9)
    doubt = verified_score(score, np.zeros(4))  # p = 0.5 halves the odds
    np.testing.assert_allclose(doubt / (1 - doubt), 0.5 * score / (1 - score))
    assert np.all(verified_score(score, np.array([-3.0, 0.0, 2.0, -8.0])) < score)
    # a bias added to the first stage's logits moves the final logits by the same amount
    logit = np.log(score / (1 - score))
    shifted = verified_score(1 / (1 + np.exp(-(logit + 1.5))), np.array([-2.0, 1.0, 0.0, 4.0]))
    plain = verified_score(score, np.array([-2.0, 1.0, 0.0, 4.0]))
    np.testing.assert_allclose(np.log(shifted / (1 - shifted)) - np.log(plain / (1 - plain)), 1.5)
    # a power w multiplies the odds by p^w: at p = 0.25, w = 0.5 halves them, and counts for less than w = 1
    quarter = np.full(4, -np.log(3.0))
    half = verified_score(score, quarter, power=0.5)
    np.testing.assert_allclose(half / (1 - half), 0.5 * score / (1 - score))
    assert np.all(verified_score(score, quarter) < half)


def test_a_model_file_without_a_verification_power_counts_the_verification_fully():
    def power(meta: dict) -> float:
        return Detector(lambda *_: None, meta=meta, backend="onnxruntime", path=None).verify_power

    assert power({"refiner": {"verify": True}}) == power({}) == 1.0  # files written before it was stored
    assert power({"refiner": {"verify": True, "verify_power": 0.5}}) == 0.5


def _bar_middles(samples) -> list[np.ndarray]:
    """Per sample, the points midway between each visible crossing and its nearest: on a bar, no crossing."""
    out = []
    for s in samples:
        v = s.visible
        d = np.linalg.norm(v[:, None] - v[None], axis=2) + np.eye(len(v)) * 1e9
        mid = 0.5 * (v + v[d.argmin(axis=1)])
        gap = np.linalg.norm(mid[:, None] - v[None], axis=2).min(axis=1)
        out.append(mid[gap > 6.0])
    return out


def test_the_second_stage_learns_to_tell_crossings_from_mined_negatives(drawn_dataset, tmp_path):
    samples = load_split(drawn_dataset, "train")
    asked = []

    def negatives_of(of_samples, images):
        assert len(of_samples) == len(images) == len(samples)
        asked.append(len(images))
        return _bar_middles(samples)

    cfg = RefineConfig(
        patch_px=16,
        widths=(8, 8, 16, 16),
        hidden=16,
        epochs=10,
        batch_size=32,
        lr=3e-3,
        threads=1,
        border_fraction=0.0,  # the verification alone: no patch borders of their own
    )
    torch.manual_seed(0)
    net, history = train_refiner(samples, tmp_path, cfg, STILL, seed=0, negatives_of=negatives_of)
    assert asked == [len(samples)] and net.verify
    assert history[-1]["verify_negatives_right"] > 0.8 and history[-1]["verify_positives_right"] > 0.8
    # on images it never saw, crossings score higher than the middles of bars
    refiner = eager.refiner(net)
    test = load_split(drawn_dataset, "test")
    on, off = [], []
    for s, middles in zip(test, _bar_middles(test), strict=True):
        rgb = read_image(s.path)
        on += list(refined(refiner, rgb, s.visible)[1])
        off += list(refined(refiner, rgb, middles)[1])
    assert np.median(on) > 0 > np.median(off), (np.median(on), np.median(off))
    assert np.mean(np.array(on) > 0) > 0.8 and np.mean(np.array(off) < 0) > 0.8
    # a stage interrupted after its fifth epoch resumes with the negatives it was given: not asked again
    payload = torch.load(tmp_path / "refine_last.pt", weights_only=False)
    payload["history"] = payload["history"][:5]
    torch.save(payload, tmp_path / "refine_last.pt")
    _, history_again = train_refiner(samples, tmp_path, cfg, STILL, seed=0, negatives_of=negatives_of)
    assert asked == [len(samples)] and len(history_again) == 10


def test_mined_negatives_are_first_stage_detections_away_from_every_crossing(trained_run, drawn_dataset):
    samples = load_split(drawn_dataset, "train")
    det = Detector.load(trained_run.out_dir)
    det.refiner = det.depth_check = None  # the first stage alone, as training mines with
    cfg = RefineConfig(negative_score=0.01, negative_gate_px=1.0)  # loose: a tiny network's detections
    images = [read_image(s.path) for s in samples]
    mined = negatives_in(first_stage_detections(det, samples, cfg, images=images), samples, cfg)
    assert len(mined) == len(samples)
    total = 0
    for s, rgb, neg in zip(samples, images, mined, strict=True):
        found = det.detect(rgb, threshold=0.01, camera=s.camera)[:, :2]
        far = np.linalg.norm(found[:, None] - s.visible[None], axis=2).min(axis=1) > 1.0
        np.testing.assert_allclose(neg, found[far])
        total += len(neg)
    assert total > 0


class _Found:
    """A stand-in first stage: the given detections (u, v, score) for each image, by file."""

    depth_check = None

    def __init__(self, by_file: dict[str, np.ndarray]):
        self.by_file = by_file
        self.paths: list[str] = []

    def detect(self, rgb, *, threshold, camera=None, depth=None, point="sight"):
        return self.by_file[self.paths.pop(0)]
