"""The lower mat's crossings, placed from a dataset's tables, where the renderer drew the lower mat."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from rebar_data.config import ConfigError
from rebar_data.dataset.layout import INSTANCE_OFFSET
from rebar_data.geometry.build import build_rebar_mesh
from rebar_data.geometry.config import MeshConfig
from rebar_data.perception.evaluation.data import load_split, read_distractors
from rebar_data.perception.evaluation.evaluate import score
from rebar_data.perception.evaluation.lower_mat import lower_mat_crossings, lower_mat_of, lower_mat_places
from rebar_data.perception.training.config import TrainConfig, resolve_config
from rebar_data.perception.training.epochs import TrainingImages, make_batch
from rebar_data.perception.training.refine import with_lower_mat
from rebar_data.scene.mat_surface import MatSurface
from rebar_data.scene.surroundings import DISTRACTOR_ID
from tests.dataset.conftest import TINY, write_config

# a planar mat with its lower mat in every scene, seen steeply from close by, as the Cycles sets see it
LOWER = {
    **TINY,
    "name": "lower",
    "mesh": {"kind": "planar", "width_m": 0.8, "height_m": 0.6, "spacing_x_m": 0.12, "spacing_y_m": 0.12},
    "camera": {
        "intrinsics": {"width": 320, "height": 240, "fx": 262.5, "fy": 262.5, "cx": 160.0, "cy": 120.0},
        "trajectories": [
            {
                "kind": "random_look_at",
                "count": 3,
                "frames": 1,
                "standoff_m": [0.45, 0.6],
                "tilt_deg": [20, 35],
            }
        ],
    },
    "scene": {
        "surroundings": {"distractors": {"lower_layer_probability": 1.0, "lower_layer_depth_m": [0.1, 0.12]}}
    },
    "dataset": {"split": {"rule": "scene", "train": 1.0, "val": 0.0, "test": 0.0}},
}


@pytest.fixture(scope="module")
def lower_dataset(tmp_path_factory):
    from rebar_data.dataset.build import build_dataset

    cfg = write_config(tmp_path_factory.mktemp("cfg"), LOWER, "lower.yaml")
    return build_dataset(cfg, tmp_path_factory.mktemp("ds"), workers=1)


def test_the_surface_through_the_crossings_is_the_one_the_scene_drew_on():
    rm = build_rebar_mesh(
        MeshConfig(
            mesh={"kind": "tunnel_segment", "width_m": 0.6, "intrados_arc_m": 0.78, "extrados_arc_m": 0.86},
            seed=3,
        )
    )
    whole, bare = MatSurface.of(rm), MatSurface.through(rm.layout, rm.crossings.point)
    assert bare.kind == whole.kind and bare.radius_m == pytest.approx(whole.radius_m)
    np.testing.assert_allclose(bare.origin_mesh, whole.origin_mesh)
    np.testing.assert_allclose(bare.crossing_ab, whole.crossing_ab)
    assert whole.height_range_m[0] < 0 < whole.height_range_m[1]


def _assert_on_drawn_lower_mat(dataset, *, apart_from_labels: bool = True) -> None:
    samples = load_split(dataset, "train")
    found = lower_mat_crossings(dataset, samples)
    assert all(len(f) >= 3 for f in found), [len(f) for f in found]
    on = near = total = 0
    for s, uv in zip(samples, found, strict=True):
        instance = cv2.imread(str(dataset / f"instances/train/{s.image_id}.png"), cv2.IMREAD_UNCHANGED)
        lower = (instance.astype(np.int32) - INSTANCE_OFFSET) == DISTRACTOR_ID
        for u, v in uv:
            i, j = int(v), int(u)
            on += bool(lower[i, j])  # the lower mat's own crossing, seen between the top bars
            near += bool(lower[max(i - 8, 0) : i + 9, max(j - 8, 0) : j + 9].any())  # or behind a top bar
            total += 1
        if apart_from_labels and len(uv) and len(s.visible):  # none of them is a labelled crossing
            assert np.linalg.norm(uv[:, None] - s.visible[None], axis=2).min() > 1.0
    assert near == total
    assert on >= 0.2 * total, (on, total)


def test_each_lower_mat_crossing_lies_on_the_drawn_lower_mat(lower_dataset):
    _assert_on_drawn_lower_mat(lower_dataset)


def test_the_lower_mat_of_a_wall_read_from_ifc_is_its_top_mat_moved_beneath(tmp_path):
    """The sample IFC wall: the lower mat copies the front mat alone, with directions from the fitted plane."""
    pytest.importorskip("ifcopenshell")
    from rebar_data.dataset.build import build_dataset
    from rebar_data.geometry.ifc_samples import write_wall

    (tmp_path / "model").mkdir()
    write_wall(tmp_path / "model/wall.ifc")
    data = {
        **LOWER,
        "name": "lower-wall",
        "mesh": {"kind": "ifc", "ifc_path": "model/wall.ifc", "crossings": "top_mat"},
        "realism": {"tie_wire_fraction": 0.3},
    }
    # the lower mat, 0.10-0.12 m down, lies about where the wall's back mat is (0.116 m behind the front one),
    # and a lower crossing can project onto a labelled one (one came within 0.7 px here)
    ds = build_dataset(write_config(tmp_path, data, "wall.yaml"), tmp_path / "ds", workers=1)
    _assert_on_drawn_lower_mat(ds, apart_from_labels=False)


def test_the_lower_mat_joins_the_mined_negatives_sampled_and_gated(lower_dataset):
    samples = load_split(lower_dataset, "train")
    twice = samples + samples[:1]
    mined = [np.array([[1.0, 2.0]]) for _ in twice]
    out = with_lower_mat(twice, mined, 2, gate_px=6.0, seed=0)
    placed = lower_mat_of(twice)
    np.testing.assert_array_equal(placed[0], placed[-1])  # one image listed twice is placed once
    for s, m, o, p in zip(twice, mined, out, placed, strict=True):
        np.testing.assert_array_equal(o[:1], m)
        extra = o[1:]
        assert len(extra) == min(2, len(p))
        assert all(np.isclose(p, e).all(axis=1).any() for e in extra)
        if len(extra) and len(s.visible):
            assert np.linalg.norm(extra[:, None] - s.visible[None], axis=2).min() > 6.0
    assert with_lower_mat(twice, mined, 0, gate_px=6.0, seed=0) is mined


def test_a_dataset_without_a_lower_mat_has_no_lower_mat_crossings(drawn_dataset):
    samples = load_split(drawn_dataset, "train")
    assert [len(f) for f in lower_mat_of(samples)] == [0] * len(samples)


def test_a_retired_setting_is_an_unknown_key():
    with pytest.raises(ConfigError, match="lower_mat_weight"):
        resolve_config({"adapt": {"lower_mat_weight": 1.0}}, {})


def test_training_images_know_their_distractors_pixels_only_when_the_gain_is_on(lower_dataset):
    samples = load_split(lower_dataset, "train")
    cfg = TrainConfig(
        batch_size=4,
        crop_px=128,
        augment={"mosaic_epochs": 0, "distractor_gain": [1.3, 1.3], "distractor_gain_probability": 1.0},
    )
    data = TrainingImages(samples, cache=True, occluded="ignore", distractors=True)
    plain = TrainingImages(samples, cache=True, occluded="ignore")
    src = data.pick(np.random.default_rng(0))
    s = next(x for x in samples if np.array_equal(x.visible, src.positives))
    instance = cv2.imread(str(s.instance_path), cv2.IMREAD_UNCHANGED).astype(np.int32) - INSTANCE_OFFSET
    np.testing.assert_array_equal(src.distractors, instance == DISTRACTOR_ID)
    assert src.distractors.mean() > 0.02  # the lower mat shows
    assert plain.pick(np.random.default_rng(0)).distractors is None
    batch = make_batch(data, np.random.default_rng(1), cfg, mosaic=False)
    assert batch[0].shape == (4, 3, 128, 128)
    assert read_distractors(replace(s, instance_path=None)) is None


def test_the_census_puts_each_false_detection_at_the_place_it_lies(lower_dataset):
    from rebar_data.perception.evaluation.false_detections import false_detection_census, format_census

    samples = load_split(lower_dataset, "train")
    places = lower_mat_places(lower_dataset, samples)
    assert sum(len(p["top_over_lower"]) for p in places) > 0 and sum(len(p["own"]) for p in places) > 0
    for p, together in zip(places, lower_mat_crossings(lower_dataset, samples), strict=True):
        np.testing.assert_array_equal(np.concatenate([p["top_over_lower"], p["own"]]), together)
    preds = []
    for k, (s, p) in enumerate(zip(samples, places, strict=True)):
        rows = [np.c_[s.visible, np.full(len(s.visible), 0.9)]]  # every crossing found
        rows += [np.c_[p[name], np.full(len(p[name]), 0.95)] for name in ("top_over_lower", "own")]
        if k == 0:
            rows.append([[2.0, 2.0, 0.95]])  # in the frame's corner
            # a second detection beside a crossing, 8 px from it and clear of the lower mat's places
            inner = s.visible[np.argmax(np.minimum(s.visible, [s.width, s.height] - s.visible).min(axis=1))]
            placed = np.concatenate([p["top_over_lower"], p["own"], [[2.0, 2.0]]])
            beside = [inner + 8.0 * np.array([np.cos(a), np.sin(a)]) for a in np.linspace(0, 2 * np.pi, 16)]
            clear = [b for b in beside if np.linalg.norm(placed - b, axis=1).min() > 7.0]
            rows.append([[*clear[0], 0.95]])
        rows.append([[s.width / 2, s.height / 2, 0.5]])  # below the cut: not counted
        preds.append(np.concatenate([np.asarray(r, float).reshape(-1, 3) for r in rows]))
    c = false_detection_census(lower_dataset, samples, preds, recall=1.0)
    assert c["reached"] and c["score"] == pytest.approx(0.9)
    assert c["true"] == sum(len(s.visible) for s in samples)
    assert c["top_over_lower"] == sum(len(p["top_over_lower"]) for p in places)
    assert c["lower_mat"] == sum(len(p["own"]) for p in places)
    assert (c["border"], c["beside_crossing"], c["elsewhere"]) == (1, 1, 0)
    assert c["false"] == c["top_over_lower"] + c["lower_mat"] + 2
    assert f"{c['false']} false detections above the score where recall reaches 1" in format_census(c)
    # removing false detections never lowers recall at precision 0.99
    assert all(v >= c["recall_at_p99"] for v in c["recall_at_p99_without"].values())
    # the top bars in front of lower bars the only false detections, scored above every crossing: recall at
    # precision 0.99 is what the metrics say, and all of it without them
    over = [
        np.r_[
            np.c_[s.visible, np.full(len(s.visible), 0.9)],
            np.c_[p["top_over_lower"], np.ones(len(p["top_over_lower"]))],
        ]
        for s, p in zip(samples, places, strict=True)
    ]
    c = false_detection_census(lower_dataset, samples, over)
    assert c["recall_at_p99"] == pytest.approx(score(samples, over, sigma=0.04)["recall_at_p99"])
    assert c["recall_at_p99"] < 1.0
    assert c["recall_at_p99_without"]["top_over_lower"] == 1.0
    assert c["recall_at_p99_without"]["lower_mat"] == c["recall_at_p99"]
    assert "1.000 without the top over lower ones" in format_census(c)
    # half the crossings found: recall 0.97 is never reached, and every prediction counts
    half = [np.c_[s.visible[::2], np.full(len(s.visible[::2]), 0.9)] for s in samples]
    c = false_detection_census(lower_dataset, samples, half)
    assert not c["reached"] and c["false"] == 0 and "never reaches 0.97" in format_census(c)
    with pytest.raises(ValueError, match="accepted: a number in"):
        false_detection_census(lower_dataset, samples, half, recall=0.0)


def test_a_dataset_without_a_lower_mat_counts_no_false_detection_there(drawn_dataset):
    from rebar_data.perception.evaluation.false_detections import false_detection_census

    samples = load_split(drawn_dataset, "train")
    preds = [
        np.r_[np.c_[s.visible, np.ones(len(s.visible))], [[s.width / 2 + 0.5, s.height / 2 + 0.5, 1.0]]]
        for s in samples
    ]
    c = false_detection_census(drawn_dataset, samples, preds)
    assert c["top_over_lower"] == c["lower_mat"] == 0
    assert c["false"] == len(samples)
