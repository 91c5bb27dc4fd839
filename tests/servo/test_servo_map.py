"""``rebar servo map``: one episode a cell, the same rows on one worker, two and Ray, resumable, its outputs."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from scipy.spatial.transform import Rotation

from rebar_data.cli import main
from rebar_data.servo.config import MapConfig, SuiteConfig
from rebar_data.servo.servo_map import cells_record
from rebar_data.servo.sweep import plan_cells, turned
from tests.servo.conftest import suite_dict

REBAR = str(Path(sys.executable).with_name("rebar"))


def _map_suite(root: Path, folder: Path, **map_over) -> Path:
    d = suite_dict(
        world={"mesh_config": str(root / "pipelines" / "paper-tunnel.yaml")},
        tcp={"approach": False},
        map={
            "modes": ["ibvs", "pbvs"],
            "base": "fixed",
            # the second point lies beyond the arm's reach from the fixed base
            "axial_m": [0.1, 1.6],
            "arc_m": [0.05, 0.05],
            "axial_steps": 2,
            "arc_steps": 1,
            "turns_deg": [0.0, 90.0],
            **map_over,
        },
    )
    d.pop("episodes")
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "map.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


def _rows(out: Path) -> pd.DataFrame:
    return pd.read_parquet(out / "map.parquet").drop(columns=["wall_s"])


def test_the_cells_span_modes_turns_views_and_the_surface():
    m = MapConfig(axial_steps=3, arc_steps=2, views=[{}, {"tilt_deg": [10, 0]}], turns_deg=[0, 45, 90])
    cells = plan_cells(m)
    assert len(cells) == m.cells == 2 * 3 * 2 * 3 * 2
    assert [c.index for c in cells] == list(range(len(cells)))
    assert [c.turn_deg for c in cells] == sorted(c.turn_deg for c in cells)  # turns outermost
    assert {c.axial_m for c in cells} == {-0.4, 0.0, 0.4} and {c.arc_m for c in cells} == {-0.4, 0.4}


def test_a_turn_turns_the_element_about_its_own_normal():
    suite = SuiteConfig.model_validate(suite_dict())
    R0 = Rotation.from_euler("xyz", suite.world.mesh_rotation_deg, degrees=True).as_matrix()
    R1 = Rotation.from_euler("xyz", turned(suite, 90.0).world.mesh_rotation_deg, degrees=True).as_matrix()
    assert np.allclose(R1[:, 2], R0[:, 2], atol=1e-9)  # the normal at the crown kept
    assert np.allclose(R1[:, 0], R0[:, 1], atol=1e-9)  # the mesh's x turned onto its y
    assert turned(suite, 0.0) is suite


def test_one_worker_two_and_ray_give_the_same_map(root, tmp_path, capsys):
    suite = _map_suite(root, tmp_path / "suite")
    one, two = tmp_path / "one", tmp_path / "two"
    assert main(["servo", "map", str(suite), "--out", str(one), "--quiet"]) == 0
    assert main(["servo", "map", str(suite), "--out", str(two), "--quiet", "--workers", "2"]) == 0
    rows = _rows(one)
    pd.testing.assert_frame_equal(rows, _rows(two))
    assert len(rows) == 8 and list(rows["index"]) == list(range(8))
    near, far = rows[rows["axial_m"] == 0.1], rows[rows["axial_m"] == 1.6]
    assert near["reachable"].all() and near["converged"].all()
    assert (near["lateral_error_m"] < 0.001).all() and (near["iterations"] > 0).all()
    assert not far["reachable"].any() and (far["reason"] == "unreachable").all()
    summary = json.loads((one / "summary.json").read_text())
    assert {m: (s["cells"], s["reachable"], s["converged"]) for m, s in summary["modes"].items()} == {
        "ibvs": (4, 2, 2),
        "pbvs": (4, 2, 2),
    }
    assert (one / "map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(pd.read_csv(one / "map.csv")) == 8
    md = (one / "map.md").read_text()
    assert "![map](map.png)" in md and "| ibvs | 90 |" in md
    assert not cells_record(one).exists()  # the record of finished cells goes once the map is written
    err = capsys.readouterr().err
    assert "ibvs: 2/4 cells reachable, 2 converged (100%)" in err

    pytest.importorskip("ray")
    ray_out = tmp_path / "ray"
    assert (
        main(
            [
                "servo",
                "map",
                str(suite),
                "--out",
                str(ray_out),
                "--quiet",
                "--backend",
                "ray",
                "--workers",
                "2",
            ]
        )
        == 0
    )
    pd.testing.assert_frame_equal(rows, _rows(ray_out))


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # as from a terminal, whatever this process inherited


def _finished_cells(record: Path) -> int:
    try:
        return len(json.loads((record / "steps.json").read_text()))
    except (OSError, ValueError):
        return 0


def test_a_stopped_map_resumes_with_the_cells_it_had_not_finished(root, tmp_path):
    suite = _map_suite(
        root, tmp_path / "suite", axial_m=[0.0, 0.2], arc_m=[0.0, 0.1], arc_steps=2, turns_deg=[0.0]
    )
    out = tmp_path / "out"
    record = cells_record(out)
    env = {**os.environ, "EGL_PLATFORM": "surfaceless"}
    cmd = [REBAR, "servo", "map", str(suite), "--out", str(out), "--quiet"]
    first = subprocess.Popen(
        cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True, preexec_fn=_default_sigint,
    )  # fmt: skip
    deadline = time.monotonic() + 240
    while _finished_cells(record) < 2 and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    os.killpg(first.pid, signal.SIGINT)
    _, stderr = first.communicate(timeout=120)
    assert first.returncode == 130, stderr[-2000:]
    assert "Traceback" not in stderr
    lines = [x for x in stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and re.fullmatch(
        r"interrupted: \d of 8 cells done and kept in .*; run the same command again to continue", lines[0]
    ), lines
    assert not out.exists()
    kept = json.loads((record / "steps.json").read_text())
    assert 2 <= len(kept) < 8
    second = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert second.returncode == 0, second.stderr[-2000:]
    assert f"{len(kept)} of 8 cells done before, reused" in second.stderr
    rows = pd.read_parquet(out / "map.parquet")
    assert list(rows["index"]) == list(range(8)) and rows["converged"].all()
    for name, step in kept.items():  # the kept cells were taken from the record, not run again
        assert rows.loc[int(name.split()[1]), "wall_s"] == step["result"]["wall_s"]
    assert not record.exists()


def test_servo_run_refuses_a_suite_with_only_a_map(root, tmp_path, capsys):
    suite = _map_suite(root, tmp_path)
    assert main(["servo", "run", str(suite), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has only a map section" in err[0] and "rebar servo map" in err[0]
    assert not (tmp_path / "run").exists()


def test_servo_map_refuses_a_suite_without_one(root, tmp_path, capsys):
    path = tmp_path / "plain.yaml"
    path.write_text(
        yaml.safe_dump(suite_dict(world={"mesh_config": str(root / "pipelines" / "paper-tunnel.yaml")}))
    )
    assert main(["servo", "map", str(path), "--out", str(tmp_path / "map")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no map section" in err[0]
    assert not (tmp_path / "map").exists()
