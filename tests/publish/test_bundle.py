from __future__ import annotations

import hashlib
import json
import re
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

from rebar_data.cli import main
from rebar_data.config import ConfigError
from rebar_data.publish.bundle import publish_dataset

SPLITS = ("train", "val", "test")  # the same names in every view: files, rows, Croissant, card


def _text(v) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def _tables(ds):
    return (
        pq.read_table(ds / "tables/samples.parquet").to_pandas().set_index("image_id"),
        pq.read_table(ds / "tables/keypoints.parquet").to_pandas(),
    )


def test_bundle_loads_in_datasets_with_rows_that_match_the_source_tables(bundle, source_dataset, tmp_path):
    datasets = pytest.importorskip("datasets")
    d = datasets.load_dataset(str(bundle), cache_dir=str(tmp_path / "hf"))
    S, K = _tables(source_dataset)
    assert sorted(d) == sorted(SPLITS)
    assert sum(len(d[s]) for s in d) == len(S) == 12
    seen = set()
    for split in d:
        for row in d[split]:
            iid = row["image_id"]
            src = S.loc[iid]
            assert src.split == split
            assert row["image"].size == (src.width, src.height) and row["image"].mode == "RGB"
            png = np.asarray(row["image"])
            assert png.shape == (src.height, src.width, 3) and png.std() > 0
            assert [row[k] for k in ("fx", "fy", "cx", "cy")] == [src.fx, src.fy, src.cx, src.cy]
            assert row["world_from_camera"] == list(src.world_from_camera)
            assert (row["scene_id"], row["trajectory_id"], row["frame"]) == (
                src.scene_id,
                src.trajectory_id,
                src.frame,
            )
            kp = K[(K.image_id == iid) & (K.visibility > 0)].sort_values("crossing_id")
            assert [k["crossing_id"] for k in row["keypoints"]] == kp.crossing_id.tolist()
            assert [(k["u"], k["v"], k["visibility"]) for k in row["keypoints"]] == list(
                zip(kp.u, kp.v, kp.visibility, strict=True)
            )
            assert sum(k["visibility"] == 2 for k in row["keypoints"]) == row["n_visible"] == src.n_visible
            for k in row["keypoints"]:
                x, y, w, h = k["bbox"]
                assert 0 <= x <= k["u"] <= x + w <= src.width and 0 <= y <= k["v"] <= y + h <= src.height
            seen.add(iid)
    assert seen == set(S.index)
    raw = d["train"].cast_column("image", datasets.Image(decode=False))[0]
    assert raw["image"]["bytes"] == (source_dataset / raw["file_name"]).read_bytes()
    files = {s: str(bundle / f"data/{s}-*.parquet") for s in SPLITS}  # as the card says
    by_files = datasets.load_dataset("parquet", data_files=files, cache_dir=str(tmp_path / "hf2"))
    assert {s: len(by_files[s]) for s in by_files} == {s: len(d[s]) for s in d}


def test_croissant_validates_and_its_record_sets_read_the_files(bundle, source_dataset):
    mlc = pytest.importorskip("mlcroissant")
    ds = mlc.Dataset(str(bundle / "croissant.json"))  # raises ValidationError on any error
    assert not ds.metadata.ctx.issues.errors and not ds.metadata.ctx.issues.warnings
    records = list(ds.records("default"))
    S, K = _tables(source_dataset)
    assert len(records) == len(S)
    splits = {r["default/image_id"].decode(): r["default/split"].decode() for r in records}
    assert splits == dict(S.split.items())
    split_rows = {_text(r["splits/split_name"]): _text(r["splits/split_url"]) for r in ds.records("splits")}
    assert set(split_rows) == set(SPLITS) and split_rows["val"].endswith("ValidationSplit"), split_rows
    first = records[0]
    assert first["default/image"].size == (160, 120)
    iid = first["default/image_id"].decode()
    assert len(first["default/keypoints"]) == int(((K.image_id == iid) & (K.visibility > 0)).sum())
    assert sum(1 for _ in ds.records("keypoints")) == len(K)
    meta = json.loads((bundle / "croissant.json").read_text())
    assert meta["conformsTo"] == "http://mlcommons.org/croissant/1.1"
    for f in meta["distribution"]:
        if f["@type"] == "cr:FileObject":
            assert hashlib.sha256((bundle / f["contentUrl"]).read_bytes()).hexdigest() == f["sha256"]


def test_coco_view_evaluates_with_pycocotools_and_yolo_view_is_complete(bundle, source_dataset):
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    info = json.loads((bundle / "meta/info.json").read_text())
    S, K = _tables(source_dataset)
    gt = COCO(str(bundle / "annotations/val.json"))
    for img in gt.loadImgs(gt.getImgIds()):
        assert (bundle / img["file_name"]).is_file()
    assert len(gt.getAnnIds()) == int(((K.split == "val") & (K.visibility == 2)).sum()) > 0
    dets = [{**a, "score": 1.0} for a in gt.loadAnns(gt.getAnnIds())]
    ev = COCOeval(gt, gt.loadRes(dets), iouType="keypoints")
    ev.params.kpt_oks_sigmas = np.array([info["oks_sigma"]])
    ev.params.maxDets = [100]  # images hold more than COCO's 20 keypoint objects
    ev.evaluate()
    ev.accumulate()
    precision = ev.eval["precision"][:, :, 0, 0, 0]  # IoU thresholds x recall, area "all"
    assert precision.mean() == pytest.approx(1.0)  # the labels scored against themselves

    data = yaml.safe_load((bundle / "data.yaml").read_text())
    assert "path" not in data and data["kpt_shape"] == [1, 3] and data["val"] == "images/val"
    for split in ("train", "val", "test"):
        images = sorted(p.stem for p in (bundle / "images" / split).glob("*.png"))
        labels = sorted(p.stem for p in (bundle / "labels" / split).glob("*.txt"))
        assert images == labels == sorted(S.index[S.split == split])


def test_checksums_list_every_file_and_match(bundle):
    lines = (bundle / "SHA256SUMS").read_text().splitlines()
    sums = dict(reversed(line.split("  ", 1)) for line in lines)
    files = {p.relative_to(bundle).as_posix() for p in bundle.rglob("*") if p.is_file()} - {"SHA256SUMS"}
    assert set(sums) == files
    for rel in (
        "README.md",
        "croissant.json",
        "data/train-00000-of-00001.parquet",
        "tables/keypoints.parquet",
    ):
        assert hashlib.sha256((bundle / rel).read_bytes()).hexdigest() == sums[rel]


def test_card_has_the_hub_header_and_says_how_the_data_was_made(bundle, source_dataset):
    text = (bundle / "README.md").read_text()
    head, body = text.split("---\n")[1], text.split("---\n", 2)[2]
    meta = yaml.safe_load(head)
    assert meta["license"] == "cc-by-4.0" and meta["size_categories"] == ["n<1K"]
    assert "keypoint-detection" in meta["task_categories"]
    files = {f["split"]: f["path"] for f in meta["configs"][0]["data_files"]}
    assert files == {s: f"data/{s}-*.parquet" for s in SPLITS}
    assert "validation" not in (bundle / "croissant.json").read_text()
    assert sorted(p.name.split("-")[0] for p in (bundle / "data").glob("*.parquet")) == sorted(SPLITS)
    info = json.loads((source_dataset / "meta/info.json").read_text())
    for section in (
        "## How it was made",
        "## Labels",
        "## Splits",
        "## Audit",
        "## Known limits",
        "## License",
    ):
        assert section in body
    for fact in (info["config_hash"], info["generator"]["git_commit"], f"Seed {info['seed']}", "sigma 0.04"):
        assert fact in body
    assert "Published 2026-01-01" in body and "passed on this data" in body
    # repeatability as measured: labels and tables exact, a few shadowed RGB frames off by a grey level or two
    assert "byte-identical labels and images" not in body
    assert "grey levels" in body and "--workers 1" in body and "--workers 2" in body
    # the COCOeval snippet is the dataset card's, word for word
    snippet = next(b for b in re.findall(r"```python\n(.*?)```", body, re.S) if "COCOeval" in b)
    assert f"kpt_oks_sigmas = np.array([{info['oks_sigma']}])" in snippet and "maxDets" in snippet
    assert snippet in (source_dataset / "README.md").read_text()
    assert (bundle / "audit/contact_sheet.png").stat().st_size > 0


def test_publish_refuses_what_it_should_and_prints_the_bundle_last(source_dataset, bundle, tmp_path, capsys):
    out = tmp_path / "again"
    assert main(["dataset", "publish", str(source_dataset), "--out", str(out), "--maps"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == str(out.resolve())
    sums = (out / "SHA256SUMS").read_text()
    depth = sorted((out / "depth").rglob("*.png"))
    assert len(depth) == 12 and all(p.relative_to(out).as_posix() in sums for p in depth)
    assert "depth/<split>/<image_id>.png" in (out / "README.md").read_text()
    assert not (bundle / "depth").exists()
    assert main(["dataset", "publish", str(source_dataset), "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err

    broken = tmp_path / "broken"
    shutil.copytree(source_dataset, broken)
    label = sorted((broken / "labels/train").glob("*.txt"))[0]
    label.write_text(label.read_text() + "0 0.5 0.5 0.1 0.1 0.5 0.5 2\n")
    with pytest.raises(ConfigError, match="does not validate"):
        publish_dataset(broken, tmp_path / "nope")
    assert not (tmp_path / "nope").exists()
    with pytest.raises(ConfigError, match="--license"):
        publish_dataset(source_dataset, tmp_path / "nope", license_id="gpl")


def test_files_other_tools_add_are_not_published_and_do_not_block_publishing(source_dataset, tmp_path):
    """A dataset Ultralytics trained on holds labels/<split>.cache (and .npy beside the images with
    cache=disk): it still publishes, and the bundle holds neither."""
    src = tmp_path / "src"
    shutil.copytree(source_dataset, src)
    (src / "labels/train.cache").write_bytes(b"\x93NUMPY cache")
    image = sorted((src / "images/train").glob("*.png"))[0]
    image.with_suffix(".npy").write_bytes(b"\x93NUMPY image")
    out = publish_dataset(src, tmp_path / "bundle")
    assert not list(out.rglob("*.cache")) and not list(out.rglob("*.npy"))
    sums = (out / "SHA256SUMS").read_text()
    assert ".cache" not in sums and ".npy" not in sums
    assert (out / "labels/train" / image.with_suffix(".txt").name).is_file()
