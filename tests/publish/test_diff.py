from __future__ import annotations

import json
import shutil

import pyarrow.parquet as pq
import pytest

from rebar_data.cli import main
from rebar_data.publish.diff import declared_bump, diff_datasets, flatten


def test_diff_of_two_builds_with_different_configs(source_dataset, next_dataset, capsys):
    d = diff_datasets(source_dataset, next_dataset)
    keys = {c["key"] for c in d.config}
    assert {"version", "camera.trajectories[0].frames", "scene.lighting.sun.illuminance_lux"} <= keys
    assert d.images["added"] == 3 and d.images["removed"] == 0 and d.images["moved"] == 0
    assert sum(d.counts[s]["images"][1] - d.counts[s]["images"][0] for s in d.counts) == 3
    sun = next(s for s in d.distributions if s.name == "light_sun_illuminance_lux")
    assert sun.shifted and sun.new["min"] >= 90000.0 > sun.old["min"]
    assert d.bump == "minor" and d.declared == "minor" and d.declared_enough
    assert main(["dataset", "diff", str(source_dataset), str(next_dataset), "--check"]) == 0
    text = capsys.readouterr().out
    assert "needs a MINOR version bump" in text and "scene.lighting.sun.illuminance_lux" in text
    assert main(["dataset", "diff", str(source_dataset), str(next_dataset), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["bump"] == "minor"


def _copy(ds, dst):
    for rel in ("meta/info.json", "tables/samples.parquet", "tables/keypoints.parquet"):
        (dst / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ds / rel, dst / rel)
    return dst


def _edit_info(ds, **changes):
    p = ds / "meta/info.json"
    info = json.loads(p.read_text())
    for k, v in changes.items():
        info[k] = v
    p.write_text(json.dumps(info))


def test_diff_says_none_patch_or_major(source_dataset, tmp_path, capsys):
    same = diff_datasets(source_dataset, source_dataset)
    assert same.bump == "none" and same.reasons == [] and same.declared_enough

    described = _copy(source_dataset, tmp_path / "described")
    info = json.loads((source_dataset / "meta/info.json").read_text())
    _edit_info(described, description="now with a description", version="0.0.2")
    assert diff_datasets(source_dataset, described).bump == "patch"

    sigma = _copy(source_dataset, tmp_path / "sigma")
    config = {**info["config"], "dataset": {**info["config"]["dataset"], "oks_sigma": 0.08}}
    _edit_info(sigma, oks_sigma=0.08, config=config, version="0.1.0")
    d = diff_datasets(source_dataset, sigma)
    assert d.bump == "major" and not d.declared_enough
    assert any(lvl == "major" and "oks_sigma" in why for lvl, why in d.reasons)
    assert main(["dataset", "diff", str(source_dataset), str(sigma), "--check"]) == 1
    assert "the changes need a major bump" in capsys.readouterr().err

    dropped = _copy(source_dataset, tmp_path / "dropped")
    t = pq.read_table(dropped / "tables/samples.parquet")
    pq.write_table(t.drop_columns(["trajectory_kind"]), dropped / "tables/samples.parquet")
    d = diff_datasets(source_dataset, dropped)
    assert d.bump == "major" and "samples.trajectory_kind removed (string)" in d.schema


def test_versions_and_flattening():
    assert declared_bump("1.2.3", "2.0.0") == "major"
    assert declared_bump("1.2.3", "1.3.0") == "minor"
    assert declared_bump("1.2.3", "1.2.4") == "patch"
    assert declared_bump("1.2.3", "1.2.3") == "none"
    assert declared_bump("1.2.3", "1.2.2") == "downgrade"
    flat = flatten({"a": {"b": [1, 2]}, "t": [{"k": 1}, {"k": 2}]})
    assert flat == {"a.b": [1, 2], "t[0].k": 1, "t[1].k": 2}


def test_diff_of_a_folder_that_is_not_a_dataset_is_one_clear_error(tmp_path, source_dataset, capsys):
    assert main(["dataset", "diff", str(tmp_path), str(source_dataset)]) == 2
    assert "meta/info.json" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["dataset", "diff", str(source_dataset)])
