"""`rebar mesh` reads the mesh through the whole pipeline schema: a file broken anywhere writes nothing."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

import rebar_data.config
from rebar_data.cli import main
from rebar_data.config import ConfigError
from rebar_data.pipeline import load_mesh_config

ROOT = Path(__file__).resolve().parents[2]


def _smoke() -> dict:
    return yaml.safe_load((ROOT / "pipelines/smoke.yaml").read_text())


def _unknown_top_level_key() -> dict:
    return {**_smoke(), "colour_grading": "warm"}


def _trajectory_count_not_a_number() -> dict:
    data = _smoke()
    data["camera"]["trajectories"][0]["count"] = "not-a-number"
    return data


BROKEN = {
    "unknown top-level key": (_unknown_top_level_key, ["unknown key", "'colour_grading'"]),
    "trajectory count not a number": (
        _trajectory_count_not_a_number,
        ["camera.trajectories.0.count", "'not-a-number'", "valid integer"],
    ),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_mesh_refuses_a_pipeline_broken_outside_the_mesh_and_writes_nothing(case, tmp_path, capsys):
    make, words = BROKEN[case]
    cfg = tmp_path / "broken.yaml"
    cfg.write_text(yaml.safe_dump(make(), sort_keys=False))
    out, rrd = tmp_path / "out" / "mesh", tmp_path / "mesh.rrd"
    assert main(["mesh", str(cfg), "--out", str(out), "--rrd", str(rrd)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith(f"error: {cfg}: "), err
    assert all(w in err for w in words), err
    assert not out.exists() and not rrd.exists() and not (tmp_path / "out").exists()


@pytest.mark.parametrize("case", list(BROKEN))
def test_load_mesh_config_checks_the_whole_pipeline(case, tmp_path):
    make, words = BROKEN[case]
    cfg = tmp_path / "broken.yaml"
    cfg.write_text(yaml.safe_dump(make(), sort_keys=False))
    with pytest.raises(ConfigError) as e:
        load_mesh_config(cfg)
    assert all(w in str(e.value) for w in words)
    # no loader of the mesh part alone is left for a command to use by mistake
    assert not hasattr(rebar_data.config, "load_mesh_config")


def test_load_mesh_config_gives_the_mesh_of_a_good_pipeline():
    cfg = load_mesh_config(ROOT / "pipelines/smoke.yaml")
    assert cfg.mesh.kind == _smoke()["mesh"]["kind"] and cfg.seed == _smoke()["seed"]
