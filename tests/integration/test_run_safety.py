"""`rebar servo run --out`: only an earlier run's folder is replaced, one writer at a time, bounded flags."""

from __future__ import annotations

import json

import pytest
import yaml

from rebar_data.cli import main
from rebar_data.outputs import OWNER_FILE, OutputLock
from tests.servo.conftest import suite_dict


@pytest.fixture
def suite(tmp_path, root, monkeypatch):
    monkeypatch.chdir(root)
    path = tmp_path / "suite.yaml"
    path.write_text(yaml.safe_dump(suite_dict()))
    return path


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("error: "), err
    return err


def test_a_folder_the_run_did_not_write_is_refused_and_kept(suite, tmp_path, capsys):
    data = tmp_path / "dataset-copy"
    (data / "images").mkdir(parents=True)
    for i in range(5):
        (data / "images" / f"{i}.png").write_bytes(b"a user's image")
    (data / "notes.txt").write_text("years of work")
    before = sorted(p.relative_to(data) for p in data.rglob("*"))
    assert main(["servo", "run", str(suite), "--out", str(data), "--quiet"]) == 2
    err = _one_error_line(capsys)
    assert "--out" in err and str(data) in err and "did not write" in err, err
    assert sorted(p.relative_to(data) for p in data.rglob("*")) == before
    assert (data / "notes.txt").read_text() == "years of work"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dataset-copy", "suite.yaml"]


def test_an_earlier_run_is_replaced_whole_and_marked(suite, tmp_path, capsys):
    out = tmp_path / "run"
    # an unmarked folder with a run's files is not this command's: refused, untouched
    out.mkdir()
    (out / "summary.json").write_text(json.dumps({"suite": "old"}))
    (out / "episodes.parquet").write_bytes(b"old")
    assert main(["servo", "run", str(suite), "--out", str(out), "--quiet"]) == 2
    assert (out / "episodes.parquet").read_bytes() == b"old"
    capsys.readouterr()
    # an earlier run (its mark) is replaced whole
    (out / OWNER_FILE).write_text(json.dumps({"command": "rebar servo run", "created_at": "earlier"}))
    (out / "episode_9.rrd").write_bytes(b"old")
    assert main(["servo", "run", str(suite), "--out", str(out), "--quiet"]) == 0
    assert json.loads((out / "summary.json").read_text())["suite"] == "test"
    assert not (out / "episode_9.rrd").exists()  # replaced whole, not written over
    assert json.loads((out / OWNER_FILE).read_text())["command"] == "rebar servo run"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run", "suite.yaml"]  # no staging, lock or old copy
    capsys.readouterr()
    # a folder with only the mark is the run's too (its files went missing)
    for p in out.iterdir():
        if p.name != OWNER_FILE:
            p.unlink()
    assert main(["servo", "run", str(suite), "--out", str(out), "--quiet"]) == 0
    assert (out / "episodes.parquet").exists()


def test_out_that_is_a_file_or_held_by_another_writer_is_one_line(suite, tmp_path, capsys):
    f = tmp_path / "results.csv"
    f.write_text("a,b\n")
    assert main(["servo", "run", str(suite), "--out", str(f), "--quiet"]) == 2
    assert "is a file" in _one_error_line(capsys)
    assert f.read_text() == "a,b\n"
    out = tmp_path / "run"
    with OutputLock(out, command="rebar servo run"):
        assert main(["servo", "run", str(suite), "--out", str(out), "--quiet"]) == 2
        assert "is writing there now" in _one_error_line(capsys)
    assert not out.exists()


@pytest.mark.parametrize("n", ["0", "-1", "two"])
def test_episodes_must_be_one_or_more(suite, tmp_path, capsys, n):
    with pytest.raises(SystemExit) as e:
        main(["servo", "run", str(suite), "--out", str(tmp_path / "run"), "--episodes", n])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--episodes" in err and ">= 1" in err, err
    assert not (tmp_path / "run").exists()


def test_check_names_a_run_it_cannot_read(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    (run / "episodes.parquet").write_bytes(b"not parquet")
    assert main(["servo", "check", str(run)]) == 2
    err = _one_error_line(capsys)
    assert str(run) in err and "cannot be read" in err, err
    f = tmp_path / "summary.json"
    f.write_text("{}")
    assert main(["servo", "check", str(f)]) == 2
    assert "is a file" in _one_error_line(capsys)
