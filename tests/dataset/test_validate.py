from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from rebar_data.cli import main
from rebar_data.dataset.validate import validate_dataset
from rebar_data.dataset.writers.manifest import write_manifest


@pytest.fixture
def copy(tiny_dataset, tmp_path):
    dst = tmp_path / "ds"
    shutil.copytree(tiny_dataset, dst)
    return dst


def _first_label(ds):
    return sorted((ds / "labels").rglob("*.txt"), key=lambda p: -p.stat().st_size)[0]


def _remove_image(ds):
    sorted((ds / "images").rglob("*.png"))[0].unlink()


def _flip_a_byte(ds):
    p = sorted((ds / "images").rglob("*.png"))[1]
    b = bytearray(p.read_bytes())
    b[len(b) // 2] ^= 0xFF
    p.write_bytes(bytes(b))


def _retype_column(ds):
    p = ds / "tables/keypoints.parquet"
    t = pq.read_table(p)
    i = t.column_names.index("visibility")
    pq.write_table(t.set_column(i, "visibility", t["visibility"].cast(pa.float32())), p)


def _move_keypoint_outside(ds):
    p = ds / "tables/keypoints.parquet"
    t = pq.read_table(p).to_pandas()
    i = t.index[t.visibility == 2][0]
    t.loc[i, "u"] = -12.5
    pq.write_table(pa.Table.from_pandas(t, schema=pq.read_schema(p), preserve_index=False), p)


def _duplicate_coco_id(ds):
    p = ds / "annotations/train.json"
    d = json.loads(p.read_text())
    d["annotations"][1]["id"] = d["annotations"][0]["id"]
    p.write_text(json.dumps(d))


def _short_yolo_line(ds):
    p = _first_label(ds)
    lines = p.read_text().splitlines()
    lines[0] = " ".join(lines[0].split()[:7])
    p.write_text("\n".join(lines) + "\n")


BREAKAGES = [
    (_remove_image, ["manifest", "is listed but missing"]),
    (_flip_a_byte, ["manifest", "does not match its sha256"]),
    (_retype_column, ["keypoints: column visibility has type float", "the schema says int8"]),
    (_move_keypoint_outside, ["keypoints:", "is outside the 160x120 image"]),
    (_duplicate_coco_id, ["coco:", "duplicate annotation id"]),
    (_short_yolo_line, ["yolo:", "has 7 fields; expected 8"]),
]


def test_a_fresh_dataset_is_valid(tiny_dataset, capsys):
    assert main(["dataset", "validate", str(tiny_dataset)]) == 0
    assert "valid" in capsys.readouterr().out


@pytest.mark.parametrize(("breaker", "words"), BREAKAGES, ids=[b.__name__.strip("_") for b, _ in BREAKAGES])
def test_each_breakage_is_a_named_failure(copy, breaker, words, capsys):
    breaker(copy)
    failures = validate_dataset(copy)
    assert any(all(w in line for w in words) for line in failures), failures
    assert main(["dataset", "validate", str(copy)]) == 1
    assert "INVALID" in capsys.readouterr().err


def test_not_a_dataset_is_a_clear_error(tmp_path, capsys):
    assert main(["dataset", "validate", str(tmp_path / "nope")]) == 2
    assert "no such folder" in capsys.readouterr().err
    (tmp_path / "notes.txt").write_text("a user's folder")
    assert main(["dataset", "validate", str(tmp_path)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "not a dataset folder" in err[0], err
    assert main(["dataset", "audit", str(tmp_path)]) == 2
    assert "not a dataset folder" in capsys.readouterr().err
    assert validate_dataset(tmp_path) == [
        f"layout: meta/info.json is missing; is {tmp_path} a dataset folder (<root>/<name>/v<version>)?"
    ]


# Damage that keeps the manifest right: each breaker damages a file and then rewrites the manifest, as
# someone who "fixes" the hashes would, so only what the files say can reveal it.


def _samples(ds):
    return pq.read_table(ds / "tables/samples.parquet").to_pandas()


def _rewrite_table(ds, name, df):
    p = ds / f"tables/{name}.parquet"
    pq.write_table(pa.Table.from_pandas(df, schema=pq.read_schema(p), preserve_index=False), p)


def _first_row(ds):
    return _samples(ds).iloc[0]


def _truncate_image(ds):
    p = ds / _first_row(ds).file_name
    p.write_bytes(p.read_bytes()[:200])


def _garble_depth(ds):
    p = ds / _first_row(ds).depth_file
    b = bytearray(p.read_bytes())
    b[60 : len(b) - 20] = bytes(len(b) - 80)  # header intact, compressed pixels zeroed
    p.write_bytes(bytes(b))


def _shrink_depth(ds):
    p = ds / _first_row(ds).depth_file
    cv2.imwrite(str(p), cv2.imread(str(p), cv2.IMREAD_UNCHANGED)[::2, ::2].copy())


def _instances_as_uint8(ds):
    p = ds / _first_row(ds).instance_file
    cv2.imwrite(str(p), cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.uint8))


def _image_with_alpha(ds):
    p = ds / _first_row(ds).file_name
    cv2.imwrite(str(p), cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2BGRA))


def _nan_depth_of_a_visible_keypoint(ds):
    k = pq.read_table(ds / "tables/keypoints.parquet").to_pandas()
    k.loc[k.index[k.visibility == 2][0], "depth_m"] = float("nan")
    _rewrite_table(ds, "keypoints", k)


def _nan_in_a_randomized_column(ds):
    s = _samples(ds)
    s.loc[3, "sensor_exposure_ev"] = float("nan")
    _rewrite_table(ds, "samples", s)


def _infinite_focal_length(ds):
    s = _samples(ds)
    s.loc[2, "fx"] = float("inf")
    _rewrite_table(ds, "samples", s)


def _visibility_three(ds):
    k = pq.read_table(ds / "tables/keypoints.parquet").to_pandas()
    k.loc[k.index[k.visibility == 2][0], "visibility"] = 3
    _rewrite_table(ds, "keypoints", k)


def _zero_width(ds):
    s = _samples(ds)
    s.loc[1, "width"] = 0
    _rewrite_table(ds, "samples", s)


def _negative_depth_of_a_visible_keypoint(ds):
    k = pq.read_table(ds / "tables/keypoints.parquet").to_pandas()
    k.loc[k.index[k.visibility == 2][0], "depth_m"] = -0.4
    _rewrite_table(ds, "keypoints", k)


def _zero_box_of_a_visible_keypoint(ds):
    k = pq.read_table(ds / "tables/keypoints.parquet").to_pandas()
    k.loc[k.index[k.visibility == 2][0], "box_size_px"] = 0.0
    _rewrite_table(ds, "keypoints", k)


def _coco_unknown_category(ds):
    p = ds / "annotations/train.json"
    d = json.loads(p.read_text())
    d["annotations"][0]["category_id"] = 7
    p.write_text(json.dumps(d))


def _coco_unknown_image(ds):
    p = ds / "annotations/train.json"
    d = json.loads(p.read_text())
    d["annotations"][0]["image_id"] = 9999
    p.write_text(json.dumps(d))


def _coco_nan_keypoint(ds):
    p = ds / "annotations/train.json"
    d = json.loads(p.read_text())
    d["annotations"][0]["keypoints"][0] = float("nan")
    p.write_text(json.dumps(d))


def _yolo_label_without_image(ds):
    label = _first_label(ds)
    (label.parent / "s999-t9-orbit_arc-f000.txt").write_text(label.read_text())


def _missing_depth_file(ds):
    (ds / _first_row(ds).depth_file).unlink()


def _missing_instance_file(ds):
    (ds / _first_row(ds).instance_file).unlink()


def _null_depth_file(ds):
    s = _samples(ds)
    (ds / s.loc[0, "depth_file"]).unlink()
    s.loc[0, "depth_file"] = None
    _rewrite_table(ds, "samples", s)


def _keypoints_in_another_split(ds):
    k = pq.read_table(ds / "tables/keypoints.parquet").to_pandas()
    first = k.image_id == k.image_id.iloc[0]
    k.loc[first, "split"] = "test" if k.split[first].iloc[0] != "test" else "train"
    _rewrite_table(ds, "keypoints", k)


HASHED_DAMAGE = [
    (_truncate_image, ["images: images/", "does not decode", "expected a PNG"]),
    (_garble_depth, ["depth: depth/", "does not decode", "expected a PNG"]),
    (_shrink_depth, ["depth: depth/", "is 80x60 uint16 1 channel", "expected 160x120 uint16 1 channel"]),
    (_instances_as_uint8, ["instances: instances/", "is 160x120 uint8 1 channel", "expected 160x120 uint16"]),
    (_image_with_alpha, ["images: images/", "uint8 4 channels", "expected 160x120 uint8 3 channels"]),
    (
        _nan_depth_of_a_visible_keypoint,
        ["keypoints: tables/keypoints.parquet column depth_m", "nan", "finite"],
    ),
    (_nan_in_a_randomized_column, ["samples: tables/samples.parquet column sensor_exposure_ev", "finite"]),
    (_infinite_focal_length, ["samples: tables/samples.parquet column fx", "inf", "expected"]),
    (_visibility_three, ["keypoints: tables/keypoints.parquet column visibility", "3", "0, 1 or 2"]),
    (_zero_width, ["samples: tables/samples.parquet column width", "0", "expected > 0"]),
    (_negative_depth_of_a_visible_keypoint, ["column depth_m", "-0.4", "expected > 0"]),
    (_zero_box_of_a_visible_keypoint, ["column box_size_px", "expected > 0"]),
    (_coco_unknown_category, ["coco: annotations/train.json", "category 7", "expected one of"]),
    (_coco_unknown_image, ["coco: annotations/train.json", "unknown image 9999"]),
    (_coco_nan_keypoint, ["coco: annotations/train.json", "keypoints", "finite"]),
    (_yolo_label_without_image, ["labels: labels/train/s999-t9-orbit_arc-f000.txt", "no row in"]),
    (_missing_depth_file, ["depth: depth/", "is missing", "depth_file of row"]),
    (_missing_instance_file, ["instances: instances/", "is missing", "instance_file of row"]),
    (_null_depth_file, ["samples: tables/samples.parquet column depth_file", "null", "store_depth"]),
    (_keypoints_in_another_split, ["keypoints: tables/keypoints.parquet column split", "expected"]),
]


@pytest.mark.parametrize(
    ("breaker", "words"), HASHED_DAMAGE, ids=[b.__name__.strip("_") for b, _ in HASHED_DAMAGE]
)
def test_damage_behind_matching_hashes_is_a_named_failure(copy, breaker, words, capsys):
    breaker(copy)
    write_manifest(copy)
    failures = validate_dataset(copy)
    assert not any(line.startswith("manifest") for line in failures), failures
    assert any(all(w in line for w in words) for line in failures), failures
    assert main(["dataset", "validate", str(copy)]) == 1
    assert "INVALID" in capsys.readouterr().err


def test_files_other_tools_add_are_notes_and_the_dataset_stays_valid(copy, capsys):
    """Ultralytics writes labels/<split>.cache when it trains on the dataset (and .npy beside the images
    with cache=disk): a dataset someone trained on is still the dataset it was."""
    (copy / "labels/train.cache").write_bytes(b"\x93NUMPY cache")
    image = sorted((copy / "images/val").glob("*.png"))[0]
    image.with_suffix(".npy").write_bytes(b"\x93NUMPY image")
    notes = []
    assert validate_dataset(copy, note=notes.append) == []
    assert len(notes) == 2 and all(n.startswith("note: ") for n in notes), notes
    assert main(["dataset", "validate", str(copy)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert any(line.startswith("note: labels/train.cache") and "Ultralytics" in line for line in out), out
    assert out[-1].endswith("valid")
