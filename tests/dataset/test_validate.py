from __future__ import annotations

import json
import shutil

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from rebar_data.cli import main
from rebar_data.dataset.validate import validate_dataset


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
    assert validate_dataset(tmp_path) == [
        f"layout: meta/info.json is missing; is {tmp_path} a dataset folder (<root>/<name>/v<version>)?"
    ]
