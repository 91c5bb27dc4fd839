"""`rebar detect` and `rebar score`: never write into their input or over what they did not write; `rebar detect`
reads past a bad image."""

from __future__ import annotations

import json
import shutil

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from rebar_data.cli import main
from rebar_data.outputs import OWNER_FILE
from rebar_data.perception.evaluation.evaluate import load_splits
from tests.perception.conftest import shipped_model_copy
from tests.read_only import read_only_fixture  # noqa: F401  (the read_only fixture)


@pytest.fixture
def model(tmp_path):
    (tmp_path / "model").mkdir()
    return shipped_model_copy(tmp_path / "model")


@pytest.fixture
def photos(drawn_dataset, tmp_path):
    """A folder of three photographs (drawn dataset frames)."""
    folder = tmp_path / "photos"
    folder.mkdir()
    for s in load_splits(drawn_dataset)[:3]:
        shutil.copy(s.path, folder / s.path.name)
    return folder


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("error: "), err
    return err


def test_out_in_the_input_is_refused_and_the_photographs_kept(photos, model, capsys):
    before = _snapshot(photos)
    for out in (photos, photos / "overlays"):
        assert main(["detect", str(photos), "--out", str(out), "--model", str(model)]) == 2
        err = _one_line(capsys)
        assert "--out" in err and "lies in the input" in err, err
        assert _snapshot(photos) == before
    one = sorted(photos.iterdir())[0]
    assert main(["detect", str(one), "--out", str(photos), "--model", str(model)]) == 2
    assert "--out" in _one_line(capsys)
    assert _snapshot(photos) == before


def test_an_images_out_is_replaced_only_when_detect_wrote_it(photos, model, tmp_path, capsys):
    user = tmp_path / "user"
    user.mkdir()
    (user / "holiday.png").write_bytes(b"a photograph")
    assert main(["detect", str(photos), "--out", str(user), "--model", str(model)]) == 2
    assert "did not write" in _one_line(capsys)
    assert _snapshot(user) == {"holiday.png": b"a photograph"}

    out = tmp_path / "overlays"
    assert main(["detect", str(photos), "--out", str(out), "--model", str(model), "--quiet"]) == 0
    assert json.loads((out / OWNER_FILE).read_text())["command"] == "rebar detect"
    (out / "stale.png").write_bytes(b"from an earlier run")
    assert main(["detect", str(photos), "--out", str(out), "--model", str(model), "--quiet"]) == 0
    assert not (out / "stale.png").exists() and len(list(out.glob("*.png"))) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model", "overlays", "photos", "user"]

    f = tmp_path / "overlays.txt"
    f.write_text("notes")
    capsys.readouterr()
    assert main(["detect", str(photos), "--out", str(f), "--model", str(model)]) == 2
    assert "is a file" in _one_line(capsys) and f.read_text() == "notes"


def test_a_read_only_out_is_one_line(photos, model, tmp_path, capsys, read_only):
    ro = read_only(tmp_path / "ro")
    assert main(["detect", str(photos), "--out", str(ro / "overlays"), "--model", str(model)]) == 2
    assert "not writable" in _one_line(capsys)
    assert main(["detect", str(photos), "--out", str(ro), "--model", str(model)]) == 2
    assert "not writable" in _one_line(capsys)
    assert list(ro.iterdir()) == []


def test_an_unreadable_image_is_named_and_the_rest_are_detected(photos, model, tmp_path, capsys):
    names = sorted(p.name for p in photos.iterdir())
    broken = photos / names[1]
    broken.write_bytes(b"\x89PNG\r\n\x1a\n not really")  # the second of three
    out = tmp_path / "overlays"
    assert main(["detect", str(photos), "--out", str(out), "--model", str(model), "--threshold", "0.01"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert sum(names[1] in line for line in err) == 1, err
    assert err[-1] == "error: 1 of 3 images could not be read", err
    stems = {n.rsplit(".", 1)[0] for n in names}
    good = stems - {names[1].rsplit(".", 1)[0]}
    assert set(json.loads((out / "cameras.json").read_text())) == good
    assert {p.stem for p in out.glob("*.png")} == good
    ids = set(pq.read_table(out / "detections.parquet").column("image_id").to_pylist())
    assert ids and ids <= good


def test_dataset_outputs_are_checked_before_any_work(drawn_dataset, model, tmp_path, capsys, read_only):
    def detect(*args: str) -> int:
        return main(["score", str(drawn_dataset), "--model", str(model), "--no-depth", "--quiet", *args])

    folder = tmp_path / "pred.parquet"
    folder.mkdir()
    assert detect("--out", str(folder)) == 2
    assert "--out" in (err := _one_line(capsys)) and "is a folder" in err, err
    assert detect("--out", str(tmp_path / "p.parquet"), "--metrics", str(tmp_path)) == 2
    assert "--metrics" in (err := _one_line(capsys)) and "is a folder" in err, err
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert detect("--out", str(blocker / "p.parquet")) == 2
    assert "--out" in _one_line(capsys)
    ro = read_only(tmp_path / "ro")
    assert detect("--out", str(ro / "p.parquet")) == 2
    assert "--out" in (err := _one_line(capsys)) and "not writable" in err, err
    assert detect("--out", str(drawn_dataset / "pred.parquet")) == 2
    assert "lies in the input" in _one_line(capsys)
    assert not (drawn_dataset / "pred.parquet").exists()

    theirs = tmp_path / "theirs.parquet"
    pq.write_table(pa.table({"id": [1, 2], "label": ["a", "b"]}), theirs)
    notes = tmp_path / "notes.json"
    notes.write_text('{"mine": true}\n')
    assert detect("--out", str(theirs)) == 2
    assert "--out" in (err := _one_line(capsys)) and "did not write" in err, err
    assert pq.read_table(theirs).column_names == ["id", "label"]
    out, metrics = tmp_path / "p.parquet", tmp_path / "m.json"
    assert detect("--out", str(out), "--metrics", str(notes)) == 2
    assert "--metrics" in (err := _one_line(capsys)) and "did not write" in err, err
    assert notes.read_text() == '{"mine": true}\n' and not out.exists()

    # its own files are replaced, and say who wrote them; a file another command marked is not its own
    pq.write_table(pa.table({"x": [1]}).replace_schema_metadata({b"written_by": b"rebar detect"}), out)
    assert detect("--out", str(out), "--split", "val") == 2
    assert "did not write" in _one_line(capsys)
    out.unlink()
    for _ in range(2):
        assert detect("--out", str(out), "--metrics", str(metrics), "--split", "val") == 0
    assert pq.read_schema(out).metadata[b"written_by"] == b"rebar score"
    assert json.loads(metrics.read_text())["written_by"] == "rebar score"
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "file", "m.json", "model", "notes.json", "p.parquet", "pred.parquet", "ro", "theirs.parquet"
    ]  # fmt: skip


def test_coco_results_are_checked_before_any_work_and_written_whole(drawn_dataset, model, tmp_path, capsys):
    def detect(*args: str, dataset=drawn_dataset) -> int:
        return main(["score", str(dataset), "--model", str(model), "--no-depth", "--quiet", *args])

    out, coco = tmp_path / "p.parquet", tmp_path / "coco.json"
    refused = [
        (["--coco-results", str(drawn_dataset / "coco.json")], "lies in the input"),
        (
            ["--coco-results", str(model.parent / "coco.json"), "--model", str(model.parent)],
            "lies in the input",
        ),
        (["--coco-results", str(model)], ".json file"),
        (["--coco-results", str(tmp_path / "coco.txt")], ".json file"),
        (["--coco-results", str(coco), "--split", "all"], "--split train, val or test"),
        (["--coco-results", str(coco), "--point", "crossing"], "sight points"),
        (["--coco-results", str(tmp_path / "m.json"), "--metrics", str(tmp_path / "m.json")], "is --metrics"),
    ]
    for extra, words in refused:
        assert detect("--out", str(out), *extra) == 2, extra
        assert "--coco-results" in (err := _one_line(capsys)) and words in err, (extra, err)
    with pytest.raises(SystemExit) as e:  # images have no COCO annotations: `rebar detect` has no such flag
        main(["detect", str(model.parent), "--out", str(tmp_path / "o"), "--coco-results", str(coco)])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and "unrecognized arguments: --coco-results" in err[-1], err
    theirs = tmp_path / "theirs.json"
    theirs.write_text('[{"image_id": 1, "bbox": [0, 0, 1, 1]}]\n')
    assert detect("--out", str(out), "--coco-results", str(theirs)) == 2
    assert "did not write" in _one_line(capsys) and theirs.read_text().startswith('[{"image_id": 1, "bbox"')
    assert not out.exists() and not coco.exists() and not (drawn_dataset / "coco.json").exists()

    # a dataset whose COCO file lacks the split's images: one line, and neither file written
    broken = tmp_path / "broken"
    shutil.copytree(drawn_dataset, broken)
    (broken / "annotations/test.json").write_text('{"images": [], "annotations": [], "categories": []}')
    assert detect("--out", str(out), "--coco-results", str(coco), dataset=broken) == 2
    assert "annotations/test.json" in (err := _one_line(capsys)) and "no image with file_name" in err, err
    assert not out.exists() and not coco.exists()

    for _ in range(2):  # its own file is replaced whole, with no temporary file left beside it
        assert detect("--out", str(out), "--coco-results", str(coco)) == 0
    assert isinstance(json.loads(coco.read_text()), list)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "broken", "coco.json", "model", "p.parquet", "theirs.json"
    ]  # fmt: skip


class _RunsCode:
    """What a hostile checkpoint pickles: unpickling it would create ``marker``."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_a_checkpoint_that_would_run_code_is_refused_before_any_runs(photos, tmp_path, capsys):
    import torch

    marker = tmp_path / "ran"
    hostile = tmp_path / "model.pt"
    torch.save({"format": "rebar-keypoint", "state_dict": {}, "payload": _RunsCode(marker)}, hostile)
    assert main(["detect", str(photos), "--out", str(tmp_path / "out"), "--model", str(hostile)]) == 2
    assert "holds more than weights and numbers" in _one_line(capsys)
    assert not marker.exists() and not (tmp_path / "out").exists()
