"""Every command that reads a pipeline, suite or settings file checks the whole file before doing anything.

Each command is driven with a file broken outside the part that command uses: one line on stderr naming the
field and the value, exit status 2, and nothing written where its output would go.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from rebar_data.cli import main
from tests.servo.conftest import suite_dict

ROOT = Path(__file__).resolve().parents[2]


def _pipeline(**changes) -> dict:
    data = yaml.safe_load((ROOT / "pipelines/smoke.yaml").read_text())
    data.update(changes)
    return data


def _trajectory_count(value) -> dict:
    data = _pipeline()
    data["camera"]["trajectories"][0]["count"] = value
    return data


# pipelines broken outside the mesh sections (what `rebar mesh` and the servo world read)
BROKEN_PIPELINES = {
    "unknown top-level key": (_pipeline(colour_grading="warm"), ["unknown key", "colour_grading"]),
    "trajectory count not a number": (
        _trajectory_count("not-a-number"),
        ["camera.trajectories.0.count", "'not-a-number'", "integer"],
    ),
    "bad render value": (_pipeline(render={"texture_size_px": 300}), ["render.texture_size_px", "300"]),
    "bad split fractions": (
        _pipeline(dataset={"split": {"train": 0.9, "val": 0.1, "test": 0.1}}),
        ["dataset.split", "sum to 1"],
    ),
}


def _write(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _one_line_naming(capsys, words) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    for w in words:
        assert w in err, (w, err)
    return err


@pytest.mark.parametrize("case", list(BROKEN_PIPELINES))
@pytest.mark.parametrize("command", ["mesh", "render", "dataset build"])
def test_pipeline_commands_refuse_a_file_broken_anywhere(command, case, tmp_path, capsys):
    data, words = BROKEN_PIPELINES[case]
    cfg = _write(tmp_path / "broken.yaml", data)
    out = tmp_path / "out"
    assert main([*command.split(), str(cfg), "--out", str(out)]) == 2
    err = _one_line_naming(capsys, words)
    assert str(cfg) in err
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.yaml"]


@pytest.mark.parametrize("case", list(BROKEN_PIPELINES))
def test_servo_run_checks_the_whole_pipeline_its_world_uses(case, tmp_path, capsys):
    data, words = BROKEN_PIPELINES[case]
    pipeline = _write(tmp_path / "broken-pipeline.yaml", data)
    suite = _write(tmp_path / "suite.yaml", suite_dict(world={"mesh_config": str(pipeline)}))
    out = tmp_path / "runs" / "o"
    assert main(["servo", "run", str(suite), "--out", str(out)]) == 2
    assert str(pipeline) in _one_line_naming(capsys, words)
    assert not (tmp_path / "runs").exists()


def test_servo_run_refuses_a_suite_broken_outside_what_its_episodes_use(tmp_path, capsys):
    # the listed episode needs no random section and no recording: both are still checked
    suite = _write(tmp_path / "suite.yaml", suite_dict(random={"count": "many"}))
    assert main(["servo", "run", str(suite), "--out", str(tmp_path / "o")]) == 2
    _one_line_naming(capsys, ["random.count", "'many'"])
    suite = _write(tmp_path / "suite.yaml", suite_dict(recording={"rrd": "none", "fps": 30}))
    assert main(["servo", "run", str(suite), "--out", str(tmp_path / "o")]) == 2
    _one_line_naming(capsys, ["unknown key", "recording.fps"])
    assert not (tmp_path / "o").exists()


def test_servo_check_refuses_a_broken_thresholds_file(tmp_path, capsys):
    bars = _write(tmp_path / "bars.yaml", {"suits": {}})
    run = tmp_path / "run"
    run.mkdir()
    assert main(["servo", "check", str(run), "--thresholds", str(bars)]) == 2
    _one_line_naming(capsys, ["unknown key", "suits"])


def test_train_refuses_broken_settings_before_making_a_run_folder(tmp_path, capsys):
    from tests.perception.synthetic import SyntheticSpec, write_synthetic_dataset

    spec = SyntheticSpec(width=96, height=72, focal_px=80.0, trajectories=3, frames=1)
    dataset = write_synthetic_dataset(tmp_path / "data", spec, seed=1)
    out = tmp_path / "runs" / "t"
    for settings, words in (
        ({"epochs": 2, "learning_rat": 0.1}, ["unknown key", "learning_rat"]),
        ({"epochs": "ten"}, ["epochs", "'ten'"]),
    ):
        cfg = _write(tmp_path / "train.yaml", settings)
        assert main(["train", str(dataset), "--config", str(cfg), "--out", str(out), "--quiet"]) == 2
        assert str(cfg) in _one_line_naming(capsys, words)
        assert not (tmp_path / "runs").exists()
