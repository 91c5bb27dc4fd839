"""The crossing-point stage: where each detection's 3D crossing point projects."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from rebar_data.camera import Intrinsics
from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import load_split, read_image
from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.inference.model_file import crossing_point_path
from rebar_data.perception.inference.refine import patch_rays
from rebar_data.perception.networks import eager
from rebar_data.perception.networks.files import export_onnx, onnx_meta
from rebar_data.perception.training.config import CrossingPointConfig
from rebar_data.perception.training.crossing_point import PatchSet, attach, batches, build
from tests.perception.conftest import STILL, TINY_TRAIN


def test_drawn_datasets_record_the_3d_crossing_points_apart_from_the_sight_points(drawn_dataset):
    samples = load_split(drawn_dataset, "train")
    gaps = np.concatenate([np.linalg.norm(s.crossings - s.visible, axis=1) for s in samples])
    assert np.isfinite(gaps).all() and 0.2 < gaps.mean() < 10.0  # a tilted camera: a few pixels apart


def test_turns_flips_and_scales_move_the_offset_and_the_ray_with_the_patch():
    """A dot drawn at the crossing point's place in each wide patch must land where the augmented offset
    says, whatever turn, flip and scale the batch drew; the ray turns and flips as the offset does."""
    cfg = CrossingPointConfig(patch_px=32, context_px=48, batch_size=64, scale=(0.8, 1.25))
    rng = np.random.default_rng(3)
    data = PatchSet.__new__(PatchSet)
    n = 64
    data.offset = rng.uniform(-8, 8, (n, 2)).astype(np.float32)
    data.rays = (data.offset / 10.0).astype(np.float32)  # a ray that must move as the offset does
    data.context = np.zeros((n, 48, 48, 3), np.uint8)
    for i, (dx, dy) in enumerate(data.offset):  # the patch centre is the pixel corner (24, 24)
        x, y = 24 + dx, 24 + dy
        data.context[
            i,
            int(np.floor(y - 1)) : int(np.floor(y + 1)) + 1,
            int(np.floor(x - 1)) : int(np.floor(x + 1)) + 1,
        ] = 255
    (x, rays, offset), *_ = list(batches(data, cfg, STILL, seed=0, epoch=1))
    x, rays, offset = x.numpy(), rays.numpy(), offset.numpy()
    for i in range(n):
        img = x[i].mean(axis=0)
        vs, us = np.nonzero(img > 60)
        w = img[vs, us]
        centroid = np.array([(us + 0.5) @ w, (vs + 0.5) @ w]) / w.sum()
        np.testing.assert_allclose(centroid, 16 + offset[i], atol=0.75)
        # the ray is the offset's direction turned and flipped alike (it is not scaled)
        cos = rays[i] @ offset[i] / (np.linalg.norm(rays[i]) * np.linalg.norm(offset[i]))
        assert cos == pytest.approx(1.0, abs=1e-5)


def test_patch_rays_are_the_normalised_pixel():
    np.testing.assert_allclose(
        patch_rays(np.array([[420.0, 140.0]]), Intrinsics(640, 480, 500.0, 400.0, 320.0, 240.0)),
        [[0.2, -0.25]],
    )


def test_onnx_crossing_point_gives_what_pytorch_gives(tmp_path):
    cfg = CrossingPointConfig(patch_px=16, widths=(4, 4, 8, 8), hidden=8)
    net = build(cfg)
    image = np.random.default_rng(1).integers(0, 256, (60, 80, 3)).astype(np.uint8)
    uv = np.array([[10.2, 12.7], [40.0, 30.0], [79.5, 59.5]])
    camera = Intrinsics(80, 60, 70.0, 70.0, 40.0, 30.0)
    in_torch = eager.crossing_point(net).points(image, uv, camera)
    onnx = model_file.read_crossing_point(export_onnx(net, tmp_path / "c.onnx"), threads=1)
    np.testing.assert_allclose(onnx.points(image, uv, camera), in_torch, atol=1e-4)
    assert in_torch.shape == (3, 2) and np.isfinite(in_torch).all()


def test_a_trained_run_ships_the_stage_and_detect_gives_the_crossing_points(
    trained_run, drawn_dataset, tmp_path
):
    out = trained_run.out_dir
    assert (out / "best.crossing.onnx").is_file() and (out / "best.crossing.pt").is_file()
    det = Detector.load(out)
    assert det.crossing_point is not None and det.meta["crossing_point"]["patch_px"] == 16
    results = json.loads((out / "results.json").read_text())
    assert set(results["results_against_crossing_points"]) == {"sight points", "crossing points"}
    s = load_split(drawn_dataset, "test")[0]
    rgb = read_image(s.path)
    sight = det.detect(rgb, threshold=1e-3, camera=s.camera)
    crossing = det.detect(rgb, threshold=1e-3, camera=s.camera, point="crossing")
    assert len(sight) and len(crossing) == len(sight)
    np.testing.assert_allclose(crossing[:, 2], sight[:, 2])  # the same detections, moved
    expected = det.crossing_point.points(rgb, sight[:, :2], s.intrinsics)
    np.testing.assert_allclose(crossing[:, :2], expected, atol=1e-6)
    with pytest.raises(ConfigError, match="point = 'middle' is not accepted"):
        det.detect(rgb, point="middle")
    lone = tmp_path / "lone"
    lone.mkdir()
    for name in ("best.onnx", "best.refine.onnx", "best.refine.int8.onnx", "best.depth.onnx"):
        shutil.copy(out / name, lone / name)
    with pytest.raises(ConfigError, match="best.crossing.onnx is missing"):
        Detector.load(lone / "best.onnx")


def test_the_stage_is_added_beside_a_model_trained_without_it(trained_run, drawn_dataset, tmp_path):
    model_dir = tmp_path / "model"
    model_dir.mkdir()
    for name in ("best.onnx", "best.refine.onnx", "best.refine.int8.onnx", "best.depth.onnx"):
        shutil.copy(trained_run.out_dir / name, model_dir / name)
    model = model_dir / "best.onnx"
    # as a model written before the stage existed: its metadata names none
    from rebar_data.perception.networks.files import update_onnx_meta

    update_onnx_meta(model, {"crossing_point": None})
    det = Detector.load(model)
    assert det.crossing_point is None
    rgb = read_image(load_split(drawn_dataset, "test")[0].path)
    with pytest.raises(ConfigError, match="has no crossing-point stage"):
        det.detect(rgb, point="crossing")
    cfg = CrossingPointConfig.model_validate(TINY_TRAIN["crossing_point"])
    stage = attach(model, load_split(drawn_dataset, "train"), tmp_path / "run", cfg, STILL, seed=0)
    assert stage == crossing_point_path(model) and stage.is_file()
    det = Detector.load(model)
    assert det.crossing_point is not None and onnx_meta(model)["crossing_point"]["patch_px"] == 16
    sight = det.detect(rgb, threshold=1e-3)
    assert len(det.detect(rgb, threshold=1e-3, point="crossing")) == len(sight)
    stage.write_bytes(stage.read_bytes() + b"\0")  # another file than the one the model names
    with pytest.raises(ConfigError, match="SHA-256 differs"):
        Detector.load(model)
    with pytest.raises(ConfigError, match="no such ONNX model"):
        attach(model_dir / "none.onnx", [], tmp_path / "run", cfg, STILL, seed=0)
