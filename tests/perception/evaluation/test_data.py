from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq

from rebar_data.perception.evaluation.data import load_split, read_image


def test_drawn_dataset_follows_the_contract_layout(drawn_dataset):
    root = drawn_dataset
    info = json.loads((root / "meta/info.json").read_text())
    assert {"name", "version", "schema_version"} <= set(info)
    samples = pq.read_table(root / "tables/samples.parquet").to_pandas()
    kp = pq.read_table(root / "tables/keypoints.parquet").to_pandas()
    for c in (
        "image_id",
        "split",
        "file_name",
        "width",
        "height",
        "fx",
        "fy",
        "cx",
        "cy",
        "world_from_camera",
        "scene_id",
        "trajectory_id",
    ):
        assert c in samples
    for c in (
        "image_id",
        "split",
        "u",
        "v",
        "visibility",
        "x_world",
        "y_world",
        "z_world",
        "depth_m",
        "box_size_px",
        "crossing_id",
    ):
        assert c in kp
    assert set(samples.split) == {"train", "val", "test"}
    assert samples.groupby("trajectory_id").split.nunique().max() == 1  # whole trajectories per split
    inside = (kp.u >= 0) & (kp.u < 192) & (kp.v >= 0) & (kp.v < 144)
    assert ((kp.visibility > 0) == inside).all()
    assert (kp.visibility == 2).sum() > 100 and (kp.visibility == 1).sum() > 0
    for split in ("train", "val", "test"):
        coco = json.loads((root / f"annotations/{split}.json").read_text())
        n = ((kp.split == split) & (kp.visibility > 0)).sum()
        assert len(coco["annotations"]) == n
    first = samples.iloc[0]
    lines = (root / "labels" / first.split / f"{first.image_id}.txt").read_text().splitlines()
    assert len(lines) == ((kp.image_id == first.image_id) & (kp.visibility > 0)).sum()
    assert all(len(x.split()) == 8 for x in lines)


def test_keypoints_reproject_from_their_world_points(drawn_dataset):
    samples = pq.read_table(drawn_dataset / "tables/samples.parquet").to_pandas().set_index("image_id")
    kp = pq.read_table(drawn_dataset / "tables/keypoints.parquet").to_pandas()
    for iid, g in kp.groupby("image_id"):
        s = samples.loc[iid]
        camera_from_world = np.linalg.inv(np.asarray(s.world_from_camera).reshape(4, 4))
        p = (
            g[["x_world", "y_world", "z_world"]].to_numpy() @ camera_from_world[:3, :3].T
            + camera_from_world[:3, 3]
        )
        np.testing.assert_allclose(s.fx * p[:, 0] / p[:, 2] + s.cx, g.u, atol=1e-6)
        np.testing.assert_allclose(p[:, 2], g.depth_m, atol=1e-9)


def test_load_split_reads_visible_and_occluded_crossings(drawn_dataset):
    train = load_split(drawn_dataset, "train")
    assert len(train) >= 6
    s = train[0]
    assert read_image(s.path).shape == (s.height, s.width, 3)
    assert s.visible.shape[1] == 2 and len(s.visible) == len(s.box_size_px)
    assert s.camera == (157.5, 157.5, 96.0, 72.0)
    assert sum(len(x.occluded) for x in train) > 0
