from __future__ import annotations

import hashlib
import json

import numpy as np
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


def test_data_yaml_tells_ultralytics_the_datasets_oks_sigma(tiny_dataset, tmp_path):
    import shutil

    import yaml

    data = yaml.safe_load((tiny_dataset / "data.yaml").read_text())
    info = DatasetInfo.read(tiny_dataset)
    # without kpt_oks_sigmas Ultralytics scores one keypoint with sigma 1/K = 1.0
    assert data["kpt_oks_sigmas"] == [info.oks_sigma] and data["kpt_shape"] == [1, 3]
    assert data["flip_idx"] == [0] and data["names"] == {0: "rebar_crossing"}
    assert {data[s] for s in ("train", "val", "test")} == {"images/train", "images/val", "images/test"}

    broken = tmp_path / "ds"
    shutil.copytree(tiny_dataset, broken)
    for value in (None, [1.0], [0.04, 0.04]):
        changed = {k: v for k, v in data.items() if k != "kpt_oks_sigmas"}
        if value is not None:
            changed["kpt_oks_sigmas"] = value
        (broken / "data.yaml").write_text(yaml.safe_dump(changed, sort_keys=False))
        failures = [f for f in validate_dataset(broken) if f.startswith("data.yaml")]
        assert failures and "kpt_oks_sigmas" in failures[0], (value, failures)


def ultralytics_root(data_yaml, *, datasets_dir):
    """The folder Ultralytics resolves a data.yaml's train/val/test against (``check_det_dataset``): its
    ``path`` when set, else the folder of the yaml file; a relative one that does not exist as given is taken
    under Ultralytics' DATASETS_DIR setting."""
    from pathlib import Path

    import yaml

    data = yaml.safe_load(data_yaml.read_text())
    root = Path(data.get("path") or data_yaml.parent)
    if not root.exists() and not root.is_absolute():
        root = datasets_dir / root
    return root


def test_a_copied_dataset_trains_from_its_own_folder_and_still_validates(tiny_dataset, tmp_path):
    """data.yaml has no path: Ultralytics reads the copy's images, wherever the folder is copied, and the file
    still matches the manifest (no edit, so validate, and publish, still accept the copy)."""
    import shutil

    import yaml

    moved = tmp_path / "elsewhere" / "tiny"
    shutil.copytree(tiny_dataset, moved)
    data = yaml.safe_load((moved / "data.yaml").read_text())
    root = ultralytics_root(moved / "data.yaml", datasets_dir=tmp_path / "ultralytics-datasets")
    for split in ("train", "val", "test"):
        images = (root / data[split]).resolve()
        assert images == (moved / "images" / split).resolve(), (split, images)
        assert sorted(p.name for p in images.glob("*.png")) == sorted(
            p.name for p in (tiny_dataset / "images" / split).glob("*.png")
        )
    assert validate_dataset(moved, note=lambda s: None) == []


def test_a_data_yaml_path_fails_from_schema_2_4_and_an_older_datasets_absolute_path_validates(
    tiny_dataset, tmp_path
):
    import shutil

    import yaml

    from rebar_data.dataset.writers.manifest import write_manifest

    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    data = yaml.safe_load((ds / "data.yaml").read_text())
    (ds / "data.yaml").write_text(yaml.safe_dump({"path": str(ds.resolve()), **data}, sort_keys=False))
    write_manifest(ds)
    failures = [f for f in validate_dataset(ds, note=lambda s: None) if f.startswith("data.yaml")]
    assert len(failures) == 1 and "path" in failures[0] and "expected no path" in failures[0], failures
    info = json.loads((ds / "meta/info.json").read_text())
    info["schema_version"] = "2.3.0"  # built before 2.4: data.yaml held the build folder, as this one does
    (ds / "meta/info.json").write_text(json.dumps(info, indent=2))
    write_manifest(ds)
    assert validate_dataset(ds, note=lambda s: None) == []


def test_a_dataset_of_the_schema_before_kpt_oks_sigmas_still_validates_with_a_note(tiny_dataset, tmp_path):
    """A 2.1 dataset was right when built: data.yaml without kpt_oks_sigmas and flip_idx is a note
    saying how to add them, not a failure; a 2.2 one without them fails."""
    import json
    import shutil

    import yaml

    from rebar_data.dataset.writers.manifest import write_manifest

    old = tmp_path / "ds"
    shutil.copytree(tiny_dataset, old)
    data = yaml.safe_load((old / "data.yaml").read_text())
    (old / "data.yaml").write_text(
        yaml.safe_dump({k: v for k, v in data.items() if k not in ("kpt_oks_sigmas", "flip_idx")})
    )
    write_manifest(old)
    assert any(
        f.startswith("data.yaml") and "kpt_oks_sigmas" in f
        for f in validate_dataset(old, note=lambda s: None)
    )
    info = json.loads((old / "meta/info.json").read_text())
    info["schema_version"] = "2.1.0"
    (old / "meta/info.json").write_text(json.dumps(info, indent=2))
    write_manifest(old)
    notes: list[str] = []
    assert validate_dataset(old, note=notes.append) == []
    assert len(notes) == 1 and "kpt_oks_sigmas or flip_idx" in notes[0] and "rebuild" in notes[0], notes


def test_dataset_card_states_the_dataset_and_its_cocoeval_snippet_scores_the_labels_as_perfect(
    tiny_dataset, tmp_path
):
    import json
    import re
    import shutil
    import subprocess
    import sys

    text = (tiny_dataset / "README.md").read_text()
    info = DatasetInfo.read(tiny_dataset)
    k = info.intrinsics
    for fact in (
        "# tiny v0.0.1",
        "160x120",
        f"fx {k['fx']}, fy {k['fy']}, cx {k['cx']}, cy {k['cy']}",
        f"sigma {info.oks_sigma} with area {info.oks_area}",
        info.conventions["visibility"],
        info.config_hash,
        "`intersection`",
        "labels/<split>/<image_id>.txt",
        "depth/<split>/<image_id>.png",
    ):
        assert fact in text, fact
    for s in ("train", "val", "test"):
        c = info.counts[s]
        row = f"| `{s}` | {c['images']} | {c['keypoints']} | {c['visible']} | {c['occluded']} | {c['outside']} |"
        assert row in text
    man = pq.read_table(tiny_dataset / "meta/manifest.parquet").to_pydict()
    assert "README.md" in man["path"]  # hashed like every other file; validate checks it

    snippet = next(b for b in re.findall(r"```python\n(.*?)```", text, re.S) if "COCOeval" in b)
    work = tmp_path / "eval"
    shutil.copytree(tiny_dataset / "annotations", work / "annotations")
    gt = json.loads((work / "annotations/val.json").read_text())
    per_image: dict[int, int] = {}
    for a in gt["annotations"]:
        per_image[a["image_id"]] = per_image.get(a["image_id"], 0) + 1
    assert max(per_image.values()) > 20  # more than COCOeval's default maxDets: the snippet must count them
    dets = [
        {k: a[k] for k in ("image_id", "category_id", "keypoints")} | {"score": 1.0}
        for a in gt["annotations"]
    ]
    (work / "predictions.json").write_text(json.dumps(dets))
    (work / "score.py").write_text(snippet)
    run = subprocess.run([sys.executable, "score.py"], cwd=work, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    ap, ap50 = (float(x) for x in re.search(r"AP ([0-9.]+) .*AP@0.5 ([0-9.]+)", run.stdout).groups())
    assert ap == pytest.approx(1.0) and ap50 == pytest.approx(1.0), run.stdout


def test_the_dataset_keeps_the_exact_and_the_sensor_depth(tiny_dataset):
    """depth/ is the exact z the labels are checked against; sensor_depth/ is what the frame's depth sensor
    reports (0 = no measurement); the samples table names the file, the model and its drawn parameters."""
    import cv2
    import pandas as pd

    from rebar_data.scene.config import DEPTH_MODELS

    S = pd.read_parquet(tiny_dataset / "tables/samples.parquet")
    assert (S.sensor_depth_file == "sensor_depth/" + S.split + "/" + S.image_id + ".png").all()
    assert S.sensor_depth_model.isin(DEPTH_MODELS).all() and S.sensor_depth_model.nunique() > 1
    assert {"sensor_depth_baseline_m", "sensor_depth_window_px", "sensor_depth_shift_x_px"} <= set(S.columns)
    differs = 0
    for row in S.itertuples():
        exact = cv2.imread(str(tiny_dataset / row.depth_file), cv2.IMREAD_UNCHANGED)
        sensed = cv2.imread(str(tiny_dataset / row.sensor_depth_file), cv2.IMREAD_UNCHANGED)
        assert sensed.dtype == np.uint16 and sensed.shape == exact.shape
        differs += not np.array_equal(exact, sensed)
    assert differs == len(S)


def test_the_audit_reports_the_sensor_depth_per_model_and_draws_it_beside_the_colour_frame(tiny_dataset):
    import pandas as pd

    S = pd.read_parquet(tiny_dataset / "tables/samples.parquet")
    checks, stats = audit_dataset(tiny_dataset)
    assert all(c.passed for c in checks)
    assert set(stats["sensor_depth"]) == set(S.sensor_depth_model)
    for model, m in stats["sensor_depth"].items():
        assert m["images"] == int((S.sensor_depth_model == model).sum())
        assert 0.0 <= m["valid_fraction_min"] <= m["valid_fraction_mean"] <= m["valid_fraction_max"] <= 1.0
    assert (tiny_dataset / "audit/sensor_depth.png").stat().st_size > 0
    assert "## Sensor depth" in (tiny_dataset / "audit/report.md").read_text()


def test_the_sensor_depth_draws_leave_the_images_and_the_exact_depth_byte_identical(tiny_dataset, tmp_path):
    """The depth sensor draws from its own stream: another sensor mix gives the same images and depth/."""
    import yaml

    from rebar_data.dataset.build import build_dataset

    from .conftest import TINY, write_config

    exact_only = {**TINY, "scene": {"depth_sensor": {"models": {"exact": 1.0}, "misregistration_px": [0, 0]}}}
    other = build_dataset(write_config(tmp_path / "cfg", exact_only), tmp_path / "out", workers=1)
    for folder in ("images", "depth"):
        files = sorted(p.relative_to(tiny_dataset) for p in (tiny_dataset / folder).rglob("*.png"))
        assert files and all((tiny_dataset / f).read_bytes() == (other / f).read_bytes() for f in files)
    for f in (other / "sensor_depth").rglob("*.png"):  # exact, unshifted: the exact depth itself
        assert f.read_bytes() == (other / "depth" / f.relative_to(other / "sensor_depth")).read_bytes()
    assert yaml.safe_load((other / "data.yaml").read_text())


def test_a_dataset_of_the_schema_before_sensor_depth_still_validates(tiny_dataset, tmp_path):
    """A 2.2 dataset has no sensor_depth/ nor its columns and validates; a 2.3 one without them fails."""
    import shutil

    import pyarrow.parquet as pq

    from rebar_data.dataset.writers.manifest import write_manifest

    old = tmp_path / "ds"
    shutil.copytree(tiny_dataset, old)
    shutil.rmtree(old / "sensor_depth")
    t = pq.read_table(old / "tables/samples.parquet")
    pq.write_table(
        t.select([c for c in t.column_names if not c.startswith("sensor_depth_")]),
        old / "tables/samples.parquet",
    )
    write_manifest(old)
    assert any("sensor_depth_file is missing" in f for f in validate_dataset(old, note=lambda s: None))
    info = json.loads((old / "meta/info.json").read_text())
    info["schema_version"] = "2.2.0"
    (old / "meta/info.json").write_text(json.dumps(info, indent=2))
    write_manifest(old)
    assert validate_dataset(old, note=lambda s: None) == []


def test_validate_names_a_sensor_depth_map_of_the_wrong_type(tiny_dataset, tmp_path):
    import shutil

    import cv2
    import pandas as pd

    from rebar_data.dataset.writers.manifest import write_manifest

    bad = tmp_path / "ds"
    shutil.copytree(tiny_dataset, bad)
    rel = pd.read_parquet(bad / "tables/samples.parquet").sensor_depth_file.iloc[0]
    cv2.imwrite(str(bad / rel), np.zeros((120, 160), np.uint8))
    write_manifest(bad)
    failures = validate_dataset(bad, note=lambda s: None)
    assert any(f.startswith("sensor_depth:") and rel in f and "uint16" in f for f in failures), failures
