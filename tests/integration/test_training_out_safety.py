"""`rebar train`, `adapt` and `add-crossing-point` write only their own run folders, one writer at a time."""

from __future__ import annotations

import json

import pytest
import yaml

from rebar_data.cli import main
from rebar_data.outputs import OWNER_FILE, OutputLock
from tests.perception.conftest import TINY_TRAIN, shipped_model_copy


@pytest.fixture
def settings(tmp_path):
    cfg = tmp_path / "train.yaml"
    cfg.write_text(yaml.safe_dump({**TINY_TRAIN, "model": {"channels": [8, 8, 16, 16], "blocks": [0, 1, 1]}}))
    return cfg


def _user_folder(path):
    path.mkdir()
    (path / "thesis.tex").write_text("years of work")
    return path


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("error: "), err
    return err


def test_train_refuses_a_folder_that_is_not_a_run_and_a_run_being_written(
    drawn_dataset, settings, tmp_path, capsys
):
    def train(out) -> int:
        args = ["--config", str(settings), "--epochs", "1", "--quiet"]
        return main(["train", str(drawn_dataset), "--out", str(out), *args])

    user = _user_folder(tmp_path / "user")
    assert train(user) == 2
    assert "--out" in (err := _one_line(capsys)) and "did not write" in err, err
    assert [p.name for p in user.iterdir()] == ["thesis.tex"]
    f = tmp_path / "run.txt"
    f.write_text("notes")
    assert train(f) == 2
    assert "is a file" in _one_line(capsys) and f.read_text() == "notes"
    assert train(drawn_dataset / "run") == 2
    assert "lies in the input" in _one_line(capsys)

    run = tmp_path / "run"
    with OutputLock(run, command="rebar train"):
        assert train(run) == 2
        assert "is writing there now" in _one_line(capsys)
    assert not run.exists()


def test_stage_commands_refuse_folders_they_did_not_write(drawn_dataset, trained_run, tmp_path, capsys):
    from tests.perception.synthetic import SyntheticSpec, write_synthetic_dataset

    spec = SyntheticSpec(width=192, height=144, focal_px=157.5, trajectories=3, frames=2)
    frames = write_synthetic_dataset(tmp_path / "data", spec, seed=6, name="drawn-other")
    model = shipped_model_copy(_user_folder(tmp_path / "model"))
    user = _user_folder(tmp_path / "user")
    for args in (
        ["adapt", str(drawn_dataset), "--frames", str(frames), "--model", str(model)],
        ["add-crossing-point", str(drawn_dataset), "--model", str(model)],
    ):
        for out in (user, trained_run.out_dir):  # a user's folder; a training run is not theirs either
            before = sorted(p.name for p in out.iterdir())
            assert main([*args, "--out", str(out), "--quiet"]) == 2, (args, out)
            assert "--out" in (err := _one_line(capsys)) and "did not write" in err, err
            assert sorted(p.name for p in out.iterdir()) == before
        assert main([*args, "--out", str(drawn_dataset / "stage"), "--quiet"]) == 2
        assert "lies in the input" in _one_line(capsys)
        out = tmp_path / "held"
        with OutputLock(out, command=args[0]):
            assert main([*args, "--out", str(out), "--quiet"]) == 2
            assert "is writing there now" in _one_line(capsys)


def test_a_run_is_marked_and_resumes_in_its_own_folder(trained_run):
    mark = json.loads((trained_run.out_dir / OWNER_FILE).read_text())
    assert mark["command"] == "rebar train"
