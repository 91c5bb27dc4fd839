from __future__ import annotations

import hashlib

import pyarrow.parquet as pq
import pytest

from rebar_data.cli import main
from rebar_data.config import ConfigError
from rebar_data.dataset import build as build_mod
from rebar_data.dataset.audit import audit_dataset
from rebar_data.dataset.build import build_dataset
from rebar_data.dataset.layout import DatasetInfo
from rebar_data.dataset.validate import validate_dataset

LABEL_PREFIXES = ("labels/", "annotations/", "tables/")


def _hashes(ds, prefixes=LABEL_PREFIXES) -> dict[str, str]:
    man = pq.read_table(ds / "meta/manifest.parquet").to_pydict()
    return {p: h for p, h in zip(man["path"], man["sha256"], strict=True) if p.startswith(prefixes)}


def test_fresh_build_validates_and_passes_its_audit(tiny_dataset):
    assert tiny_dataset.name == "v0.0.1" and tiny_dataset.parent.name == "tiny"
    assert validate_dataset(tiny_dataset) == []
    checks, stats = audit_dataset(tiny_dataset)
    assert all(c.passed for c in checks), [c for c in checks if not c.passed]
    assert stats["images"] == 12
    for f in ("report.json", "report.md", "contact_sheet.png", "keypoints_per_image.png", "coverage.png"):
        assert (tiny_dataset / "audit" / f).stat().st_size > 0
    info = DatasetInfo.read(tiny_dataset)
    assert info.split["rule"] == "scene"
    assert {s: info.counts[s]["images"] for s in ("train", "val", "test")} == {
        "train": 4,
        "val": 4,
        "test": 4,
    }
    assert info.oks_sigma > 0 and info.config_hash and info.generator["git_commit"]
    assert sum(info.counts[s]["visible"] for s in info.counts) > 50


def test_two_workers_give_byte_identical_labels_and_tables(tiny_config, tiny_dataset, tmp_path):
    two = build_dataset(tiny_config, tmp_path, workers=2)
    assert _hashes(two) == _hashes(tiny_dataset)
    assert _hashes(two, ("images/",)) == _hashes(tiny_dataset, ("images/",))


def test_build_prints_the_dataset_folder_last_and_refuses_to_overwrite(tiny_config, tmp_path, capsys):
    assert main(["dataset", "build", str(tiny_config), "--out", str(tmp_path), "--workers", "1"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert out[-1] == str((tmp_path / "tiny" / "v0.0.1").resolve())
    assert main(["dataset", "build", str(tiny_config), "--out", str(tmp_path), "--workers", "1"]) == 2
    assert "already exists" in capsys.readouterr().err
    before = (tmp_path / "tiny/v0.0.1/meta/info.json").stat().st_mtime_ns
    assert (
        main(["dataset", "build", str(tiny_config), "--out", str(tmp_path), "--workers", "1", "--force"]) == 0
    )
    assert (tmp_path / "tiny/v0.0.1/meta/info.json").stat().st_mtime_ns != before


def test_interrupted_build_leaves_no_finished_folder_and_resumes_to_the_same_dataset(
    tiny_config, tiny_dataset, tmp_path, monkeypatch
):
    real_save = build_mod._save_records
    calls = []

    def save_then_die(staging, tid, records):
        real_save(staging, tid, records)
        calls.append(tid)
        if len(calls) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(build_mod, "_save_records", save_then_die)
    with pytest.raises(KeyboardInterrupt):
        build_dataset(tiny_config, tmp_path, workers=1)
    monkeypatch.setattr(build_mod, "_save_records", real_save)
    assert not (tmp_path / "tiny" / "v0.0.1").exists()
    assert (tmp_path / "tiny" / ".v0.0.1.partial").is_dir()
    with pytest.raises(ConfigError, match="--resume"):
        build_dataset(tiny_config, tmp_path, workers=1)
    resumed = build_dataset(tiny_config, tmp_path, workers=1, resume=True)
    assert _hashes(resumed) == _hashes(tiny_dataset)
    assert validate_dataset(resumed) == []
    assert not (tmp_path / "tiny" / ".v0.0.1.partial").exists()


def test_resume_refuses_a_different_config(tiny_config, tmp_path):
    staging = tmp_path / "tiny" / ".v0.0.1.partial"
    staging.mkdir(parents=True)
    (staging / "plan.json").write_text('{"config_hash": "something else"}')
    with pytest.raises(ConfigError, match="different config"):
        build_dataset(tiny_config, tmp_path, workers=1, resume=True)


def test_images_hash_matches_the_samples_table(tiny_dataset):
    s = pq.read_table(tiny_dataset / "tables/samples.parquet").to_pydict()
    for fn, digest in zip(s["file_name"], s["image_sha256"], strict=True):
        assert hashlib.sha256((tiny_dataset / fn).read_bytes()).hexdigest() == digest
