"""The render engine choice: recorded in info.json, refused cleanly when its package is missing, and a
Cycles build that validates with every image in the test split."""

from __future__ import annotations

import copy
import sys

import pytest

from rebar_data.cli import main
from rebar_data.dataset.layout import DatasetInfo
from rebar_data.dataset.validate import validate_dataset
from tests.dataset.conftest import TINY, write_config


def _cycles_config(folder, **dataset):
    data = copy.deepcopy(TINY)
    data["name"] = "tiny-cycles"
    data["render"] = {"engine": "cycles", "cycles": {"samples": 4, "denoise": False, "threads": 2}}
    data["camera"]["trajectories"] = [
        {"kind": "random_look_at", "count": 2, "frames": 1, "edge_margin_m": 0.1}
    ]
    data["dataset"] = dataset or {"split": {"rule": "scene", "train": 0.0, "val": 0.0, "test": 1.0}}
    return write_config(folder, data, "tiny-cycles.yaml")


def test_info_records_the_open3d_renderer(tiny_dataset):
    info = DatasetInfo.read(tiny_dataset)
    assert info.renderer["engine"] == "open3d" and info.renderer["open3d"]
    assert info.schema_version == "2.4.0"


def test_cycles_without_bpy_is_one_line_exit_2_and_nothing_written(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "bpy", None)  # import bpy raises ImportError
    cfg = _cycles_config(tmp_path / "cfg")
    out = tmp_path / "out"
    assert main(["dataset", "build", str(cfg), "--out", str(out), "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "render.engine: cycles" in err[0] and "pip install -e '.[cycles]'" in err[0]
    assert not out.exists()


def test_cycles_build_validates_with_every_image_in_test(tmp_path):
    pytest.importorskip("bpy", reason="Blender's bpy module is not installed (pip install -e '.[cycles]')")
    from rebar_data.dataset.build import build_dataset

    ds = build_dataset(_cycles_config(tmp_path / "cfg"), tmp_path / "out", workers=1)
    assert validate_dataset(ds) == []
    info = DatasetInfo.read(ds)
    assert info.renderer["engine"] == "cycles" and info.renderer["samples"] == 4
    assert info.renderer["blender"].startswith("4.2")
    assert info.counts["test"]["images"] == 2 and info.counts["train"]["images"] == 0
