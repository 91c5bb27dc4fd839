from __future__ import annotations

import json
import shutil
import warnings

import numpy as np
import pytest
import torch

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import load_split, read_depth, read_image
from rebar_data.perception.evaluation.evaluate import first_stage_only
from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.checks import (
    DepthCheck,
    as_depth_m,
    encode_depth,
)
from rebar_data.perception.inference.detector import Detector, shifted_score
from rebar_data.perception.inference.refine import patches
from rebar_data.perception.networks import eager
from rebar_data.perception.networks.files import export_onnx
from rebar_data.perception.training.config import DepthCheckConfig
from rebar_data.perception.training.depth_check import (
    PaddedDepth,
    build,
    depth_batches,
    epoch_depth,
    train_depth_check,
)
from tests.perception.conftest import TINY_TRAIN


def test_a_patch_is_depth_relative_to_its_centre_with_a_mask_of_measurements():
    p = np.full((2, 8, 8), 1.0, np.float32)
    p[0, :, :2] = 1.2  # a lower bar 0.2 m behind
    p[0, 0, 7] = 0.0  # no measurement
    p[1, 2:6, 2:6] = 0.0  # nothing measured at the second patch's centre
    x, has_centre = encode_depth(p, scale_m=0.05, clip=3.0)
    assert x.shape == (2, 2, 8, 8) and x.dtype == np.float32
    assert has_centre.tolist() == [True, False]
    assert x[0, 0, 4, 4] == 0.0 and x[0, 0, 4, 0] == pytest.approx(3.0)  # 4 units, clipped to 3
    assert x[0, 0, 0, 7] == 0.0 and x[0, 1, 0, 7] == 0.0 and x[0, 1, 4, 4] == 1.0
    doubled, _ = encode_depth(p, scale_m=0.05, clip=10.0, gain=np.array([2.0, 1.0]))
    assert doubled[0, 0, 4, 0] == pytest.approx(8.0)


def test_the_reference_depth_is_the_median_of_the_centres_measurements():
    rng = np.random.default_rng(0)
    p = rng.uniform(0.5, 2.0, (300, 16, 16)).astype(np.float32)
    p[rng.uniform(size=p.shape) < 0.5] = 0.0  # about half the pixels, and some whole centres, unmeasured
    p[:10, 6:10, 6:10] = 0.0
    x, has_centre = encode_depth(p, scale_m=0.05, clip=100.0)
    centre = p[:, 6:10, 6:10].reshape(len(p), -1)
    assert has_centre.tolist() == (centre > 0).any(axis=1).tolist() and not has_centre[:10].any()
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = np.nan_to_num(np.nanmedian(np.where(centre > 0, centre, np.nan), axis=1))
    np.testing.assert_allclose(x[:, 0], (p - ref[:, None, None]) / 0.05 * (p > 0), atol=1e-4)


def test_depth_patches_are_cut_as_colour_patches_are():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 2.0, (30, 40)).astype(np.float32)
    points = np.array([[10.2, 12.7], [0.4, 29.9], [39.6, 3.0]])
    cut, corners = patches(depth, points, 8)
    colour, colour_corners = patches(np.repeat(depth[:, :, None], 3, axis=2), points, 8)
    np.testing.assert_array_equal(cut, colour[..., 0])
    np.testing.assert_array_equal(corners, colour_corners)
    padded = PaddedDepth(depth, 8)  # training's cut: the same pixels, kept in millimetres
    for p, c in zip(points, cut, strict=True):
        np.testing.assert_allclose(padded.patch(p), c, atol=5e-4)


def test_depth_images_in_metres_or_millimetres_and_one_error_for_a_wrong_one():
    mm = np.array([[0, 1500], [700, 65535]], np.uint16)
    np.testing.assert_allclose(as_depth_m(mm, (2, 2)), [[0.0, 1.5], [0.7, 65.535]], rtol=1e-6)
    m = np.array([[np.nan, -1.0], [0.7, np.inf]])
    np.testing.assert_allclose(as_depth_m(m, (2, 2)), [[0.0, 0.0], [0.7, 0.0]], rtol=1e-6)
    with pytest.raises(ConfigError, match=r"registered to the colour image, here \(3, 2\)"):
        as_depth_m(mm, (3, 2))
    with pytest.raises(ConfigError, match="uint16 millimetres"):
        as_depth_m(mm.astype(np.int32), (2, 2))


def test_a_detection_with_no_depth_at_its_centre_keeps_its_score():
    seen = []

    def run(x):
        seen.append(len(x))
        return np.full(len(x), -2.0, np.float32)

    check = DepthCheck(run, patch_px=8, scale_m=0.05, clip=4.0)
    depth = np.ones((20, 20), np.float32)
    depth[:8, :8] = 0.0
    logits, share = check.logits(depth, np.array([[3.0, 3.0], [12.0, 12.0]]))
    assert logits.tolist() == [np.inf, -2.0] and seen == [1]
    assert share.tolist() == [0.0, 1.0]
    assert check.veto(depth, np.array([[3.0, 3.0]])).tolist() == [0.0]
    assert check.logits(depth, np.zeros((0, 2)))[0].shape == (0,)


def test_the_depth_check_only_lowers_a_score_when_confident_over_a_measured_patch():
    """The veto is power * share**2 * min(0, logit + margin): nothing above -margin, and a patch half
    measured counts a quarter as hard as a whole one."""
    check = DepthCheck(lambda x: np.full(len(x), -6.0, np.float32), patch_px=8, scale_m=0.05, clip=4.0)
    assert (check.power, check.margin) == (0.5, 2.0)
    depth = np.ones((20, 40), np.float32)
    depth[:, 24:28] = 0.0  # half of the second point's patch has no measurement
    veto = check.veto(depth, np.array([[10.0, 10.0], [24.0, 10.0]]))
    np.testing.assert_allclose(veto, [0.5 * (-4.0), 0.5 * 0.25 * (-4.0)])
    mild = DepthCheck(lambda x: np.full(len(x), -1.5, np.float32), patch_px=8, scale_m=0.05, clip=4.0)
    assert mild.veto(depth, np.array([[10.0, 10.0]])).tolist() == [0.0]


def test_onnx_depth_check_gives_what_pytorch_gives(tmp_path):
    torch.manual_seed(1)
    net = build(DepthCheckConfig(patch_px=16, widths=(4, 4, 8, 8), hidden=8)).eval()
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
    depth = np.random.default_rng(0).uniform(0.5, 1.0, (40, 50)).astype(np.float32)
    points = np.array([[10.0, 12.0], [25.5, 30.25], [0.5, 39.0]])
    onnx_check = model_file.read_depth_check(
        export_onnx(net, tmp_path / "d.onnx"), threads=1, scale_m=0.05, clip=4.0
    )
    assert onnx_check.patch_px == 16
    np.testing.assert_allclose(
        onnx_check.logits(depth, points)[0],
        eager.depth_check(net, scale_m=0.05, clip=4.0).logits(depth, points)[0],
        atol=1e-4,
    )


def test_depth_batches_hold_every_crossing_and_negative_once_an_epoch(drawn_dataset):
    samples = load_split(drawn_dataset, "train")[:3]
    negatives = [np.array([[5.0, 5.0]]), np.zeros((0, 2)), np.array([[50.0, 40.0], [60.0, 20.0]])]
    cfg = DepthCheckConfig(patch_px=16, batch_size=16, epochs=2)
    fixed = [PaddedDepth(read_depth(s.depth_path), cfg.patch_px) for s in samples]

    def depths(epoch):
        return fixed

    batches = list(depth_batches(depths, samples, negatives, cfg, seed=0, first=1))
    per_epoch = -(-(sum(len(s.visible) for s in samples) + 3) // 16)
    assert len(batches) == 2 * per_epoch
    labels = torch.cat([y for _, y in batches[:per_epoch]])
    assert int((labels == 0).sum()) == 3 and int(labels.sum()) == sum(len(s.visible) for s in samples)
    assert batches[0][0].shape[1:] == (2, 16, 16)
    resumed = list(depth_batches(depths, samples, negatives, cfg, seed=0, first=2))
    torch.testing.assert_close(resumed[0][0], batches[per_epoch][0])


def test_the_depth_check_learns_crossings_from_points_far_behind_the_bars(drawn_dataset, tmp_path):
    """Negatives here are points on the ground far behind the bars (the drawn data has no lower mat): the
    depth check learns to tell them from the crossings, from depth alone."""
    samples = load_split(drawn_dataset, "train")
    negatives = []
    for s in samples:
        rng = np.random.default_rng(len(negatives))
        depth = read_depth(s.depth_path)
        # the ground, far behind the bars: a point there is "a bar over the mat beneath" in depth
        ground = np.argwhere(depth > np.percentile(depth[depth > 0], 90))[:, ::-1] + 0.5
        negatives.append(ground[rng.choice(len(ground), size=min(20, len(ground)), replace=False)])
    cfg = DepthCheckConfig(patch_px=16, widths=(8, 8, 16, 16), hidden=16, epochs=6, batch_size=64, threads=1)
    net, history = train_depth_check(samples, negatives, tmp_path, cfg, seed=0)
    assert history[-1]["loss"] < history[0]["loss"]
    check = eager.depth_check(net, scale_m=cfg.scale_m, clip=cfg.clip)
    s = load_split(drawn_dataset, "test")[0]
    depth = read_depth(s.depth_path)
    assert np.median(check.logits(depth, s.visible)[0]) > 0
    far = np.argwhere(depth > np.percentile(depth[depth > 0], 95))[:, ::-1][:10] + 0.5
    assert np.median(check.logits(depth, far)[0]) < 0
    again, rerun = train_depth_check(samples, negatives, tmp_path, cfg, seed=0)  # finished: kept as it is
    assert rerun == history


def test_a_trained_run_ships_its_depth_check_and_detect_uses_it_only_with_depth(
    trained_run, drawn_dataset, tmp_path
):
    out = trained_run.out_dir
    assert (out / "best.depth.onnx").is_file() and (out / "best.depth.pt").is_file()
    det = Detector.load(out)
    assert (
        det.depth_check is not None
        and det.meta["depth_check"]["patch_px"] == TINY_TRAIN["depth_check"]["patch_px"]
    )
    results = json.loads((out / "results.json").read_text())
    assert "test" in results["results_without_depth"] and results["depth_check_parameters"] > 0
    s = load_split(drawn_dataset, "test")[0]
    rgb, depth = read_image(s.path), read_depth(s.depth_path)
    # one operating point, the RGB stages' own, with depth or without; the veto's settings as trained
    assert det.score_bias == det.meta["score_bias"] and "score_bias_without_depth" not in det.meta
    assert (det.depth_check.power, det.depth_check.margin) == (0.5, 2.0)
    without = det.detect(rgb, threshold=1e-4)
    with_depth = det.detect(rgb, threshold=1e-4, depth=depth)
    assert len(with_depth)
    # the same detections, their scores lowered by the depth check's veto and cut at the threshold; the
    # tiny check is not confident, so its margin is set where it doubts half of them
    logits = det.depth_check.logits(depth, without[:, :2])[0]
    det.depth_check.margin = -float(np.median(logits[np.isfinite(logits)]))
    with_depth = det.detect(rgb, threshold=1e-4, depth=depth)
    veto = det.depth_check.veto(depth, without[:, :2])
    assert (veto <= 0).all() and (veto < 0).any()
    expected = without.copy()
    expected[:, 2] = shifted_score(without[:, 2], veto)
    expected = expected[expected[:, 2] >= 1e-4]
    np.testing.assert_allclose(with_depth, expected[np.argsort(-expected[:, 2], kind="stable")])
    # with no measurement anywhere (a camera nearer than its sensor's range) it is the RGB stages alone
    np.testing.assert_allclose(det.detect(rgb, threshold=1e-4, depth=np.zeros_like(depth)), without)
    with pytest.raises(ConfigError, match="registered to the colour image"):
        det.detect(rgb, depth=depth[:-1])
    with first_stage_only(det):
        assert det.depth_check is None
    assert det.depth_check is not None
    lone = tmp_path / "lone"
    lone.mkdir()
    for name in ("best.onnx", "best.refine.onnx", "best.refine.int8.onnx"):
        shutil.copy(out / name, lone / name)
    with pytest.raises(ConfigError, match="best.depth.onnx is missing"):
        Detector.load(lone / "best.onnx")


def test_a_checkpoint_reads_its_depth_check_as_its_onnx_file_does(trained_run):
    """A run's .pt checkpoint and .onnx file take the depth check's patch and veto from the same meta entry."""
    out = trained_run.out_dir
    from_files, from_checkpoint = Detector.load(out, threads=1), Detector.load(out / "best.pt")

    def settings(check: DepthCheck) -> tuple:
        return check.patch_px, check.scale_m, check.clip, check.power, check.margin

    assert settings(from_checkpoint.depth_check) == settings(from_files.depth_check)
    entry = {"patch_px": 32, "scale_m": 0.05, "clip": 4.0, "veto_power": 0.8, "veto_margin": 1}
    want = {"scale_m": 0.05, "clip": 4.0, "power": 0.8, "margin": 1.0}
    assert model_file.depth_check_settings(entry) == want


def test_each_epoch_gives_an_image_its_own_sensor_depth_or_a_drawn_sensors(drawn_dataset):
    """The depth check learns from every sensor model: over epochs an image's depth is its dataset's, exact, or
    a drawn sensor's (holes where the exact depth has none), the same for the same (seed, epoch, image)."""
    s = load_split(drawn_dataset, "train")[0]
    exact = read_depth(s.depth_path)
    cfg = DepthCheckConfig(dataset_share=0.0)
    seen = [epoch_depth(s, 0, epoch, cfg, seed=3) for epoch in range(1, 13)]
    holes = [float(np.mean((d == 0) & (exact > 0))) for d in seen]
    assert max(holes) > 0.001  # a drawn sensor lost measurements the exact depth has
    assert len({round(h, 4) for h in holes}) >= 3  # and the sensors differ from epoch to epoch
    assert not all(np.array_equal(seen[0], d) for d in seen[1:])
    np.testing.assert_array_equal(epoch_depth(s, 0, 5, cfg, seed=3), seen[4])
    own = DepthCheckConfig(drawn_sensors=())  # none drawn: the dataset's own depth every epoch
    np.testing.assert_array_equal(epoch_depth(s, 0, 1, own, seed=3), exact)
