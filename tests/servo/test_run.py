"""End to end: `rebar servo run` and `rebar servo check` on a short suite and on eval/ci.yaml."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

from rebar_data.cli import main

from .conftest import suite_dict

EPISODE_COLUMNS = [
    "suite",
    "episode",
    "target_id",
    "mode",
    "converged",
    "iterations",
    "initial_error_px",
    "final_error_px",
    "final_true_error_px",
    "final_true_lateral_error_m",
    "initial_error_m",
    "final_error_m",
    "wall_s",
]


def _rerun() -> str:
    return str(Path(sys.executable).parent / "rerun")


def _goals(run: Path) -> None:
    """The issue's goals, read from the simulator's ground truth (as the acceptance check does)."""
    E = pq.read_table(run / "episodes.parquet").to_pandas()
    for mode, px, m, it in (("ibvs", 1.0, 0.001, 30), ("pbvs", None, 0.002, 40)):
        g = E[E["mode"] == mode]
        assert len(g) and g["converged"].all(), mode
        assert g["final_true_lateral_error_m"].max() <= m
        assert np.median(g["iterations"]) <= it
        if px is not None:
            assert g["final_error_px"].max() <= px
    assert (E.loc[E["mode"] == "pbvs", "final_true_error_m"] <= 0.002).all()


def test_short_run_writes_every_output_and_readable_recordings(tmp_path, root, monkeypatch, capsys):
    monkeypatch.chdir(root)
    suite = suite_dict(
        name="short",
        recording={"rrd": "episodes", "jpeg_quality": 60},
        episodes=[
            {"mode": "ibvs", "start": {"look_at_m": [0.03, -0.02], "standoff_m": 0.6}, "targets": 1},
            {"mode": "pbvs", "start": {"look_at_m": [-0.04, 0.03], "standoff_m": 0.58}, "targets": 1},
        ],
    )
    path = tmp_path / "short.yaml"
    path.write_text(yaml.safe_dump(suite))
    out = tmp_path / "run"
    assert main(["servo", "run", str(path), "--out", str(out), "--quiet"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == str(out)
    for name in ("episodes.parquet", "steps.parquet", "summary.json", "report.md"):
        assert (out / name).stat().st_size > 0, name
    E = pq.read_table(out / "episodes.parquet")
    assert set(EPISODE_COLUMNS) <= set(E.column_names)
    S = pq.read_table(out / "steps.parquet").to_pandas()
    assert {"servo", "approach", "tie", "retract"} == set(S["phase"])
    V = E.to_pandas()
    assert V["tcp_reached"].all() and (V["tcp_error_m"] < 0.002).all()  # the tool on the crossing
    assert (V["max_joint_position_ratio"] <= 1.0).all() and (V["max_joint_speed_ratio"] <= 1.0 + 1e-6).all()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["suite"] == "short" and summary["modes"]["ibvs"]["converged"] == 1
    report = (out / "report.md").read_text()
    assert "Table 1" in report and "Table 2" in report
    for png in ("ibvs_convergence.png", "pbvs_convergence.png", "ibvs_views.png"):
        assert (out / png).stat().st_size > 10_000
    rrds = sorted(out.glob("*.rrd"))
    assert len(rrds) == 2
    for f in rrds:
        r = subprocess.run([_rerun(), "rrd", "verify", str(f)], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
    from rerun.chunk import RrdReader

    chunks = list(RrdReader(rrds[0]).stream())
    entities = {c.entity_path for c in chunks}
    for e in (
        "/world/camera/image",
        "/world/camera/image/depth",
        "/world/camera/image/detections",
        "/world/camera/image/track",
        "/metrics/error_px",
        "/joints/q/elbow",
        "/world/mesh",
        "/world/robot/link_3",
    ):
        assert e in entities, e
    _check_recording(chunks, n_steps=int((S["episode"] == 0).sum()))
    assert main(["servo", "check", str(out)]) == 0
    _goals(out)


def _column(chunks, entity: str, component: str) -> list:
    """Every row's value of one component on one entity (temporal and static chunks alike)."""
    out = []
    for c in chunks:
        if c.entity_path == entity:
            rb = c.to_record_batch()
            if component in rb.schema.names:
                out += [v for v in rb.column(component).to_pylist() if v is not None]
    return out


def _check_recording(chunks, *, n_steps: int) -> None:
    """The viewer's panels have something to show, and the file is written compacted."""
    import cv2

    events = [c for c in chunks if c.entity_path == "/events"]
    # a static TextLog on the entity would shadow every temporal one: the events view would stay empty
    assert events and not any(c.is_static for c in events)
    texts = [t[0] for t in _column(events, "/events", "TextLog:text")]
    assert any(t.startswith("short episode 0") for t in texts), texts
    assert any(t.startswith("visit 0:") for t in texts), texts
    assert all("step" in c.timeline_names for c in events)

    depth = "/world/camera/image/depth"
    meters = {m[0] for m in _column(chunks, depth, "EncodedDepthImage:meter")}
    ranges = {tuple(r[0]) for r in _column(chunks, depth, "EncodedDepthImage:depth_range")}
    assert meters == {1000.0} and len(ranges) == 1
    near_m, far_m = (x / 1000.0 for x in ranges.pop())
    assert 0.4 <= near_m < far_m <= 4.5  # within the Kinect's 0.5-4.5 m
    for blob in _column(chunks, depth, "EncodedDepthImage:blob"):
        mm = cv2.imdecode(np.frombuffer(bytes(blob[0]), np.uint8), cv2.IMREAD_UNCHANGED)
        lo, hi = np.percentile(mm[mm > 0] / 1000.0, [1, 99])
        assert near_m <= lo and hi <= far_m  # what the camera sees is inside the colour scale

    # logged step by step, the batcher wrote a chunk per entity for every flush (about one per step)
    per_entity: dict[str, int] = {}
    for c in chunks:
        per_entity[c.entity_path] = per_entity.get(c.entity_path, 0) + 1
    worst = max(per_entity, key=per_entity.get)
    # (a curve: its static style, its values, and the clears that end each visit's curve)
    assert per_entity[worst] <= 3 + n_steps // 100, (worst, per_entity[worst], n_steps)


def test_ci_suite_meets_the_goals_and_its_check(tmp_path, root, monkeypatch):
    """eval/ci.yaml as CI runs it: the project's renderer, the full loop, the bars of eval/thresholds.yaml."""
    monkeypatch.chdir(root)
    out = tmp_path / "ci"
    assert main(["servo", "run", "eval/ci.yaml", "--out", str(out), "--quiet"]) == 0
    assert main(["servo", "check", str(out)]) == 0
    _goals(out)


def test_ifc_wall_suite_converges_on_the_front_mat_of_a_model_read_from_ifc(tmp_path, root, monkeypatch):
    """eval/ifc-wall.yaml: the sample IFC wall stood where the tunnel stands; its targets are the crossings of
    the mat on the model's camera side, which the world's pose turns towards the robot."""
    pytest.importorskip("ifcopenshell")
    from rebar_data.servo.config import load_suite
    from rebar_data.servo.world import build_world_mesh

    monkeypatch.chdir(root)
    out = tmp_path / "ifc"
    assert main(["servo", "run", "eval/ifc-wall.yaml", "--out", str(out), "--quiet"]) == 0
    assert main(["servo", "check", str(out)]) == 0
    _goals(out)
    suite = load_suite(root / "eval/ifc-wall.yaml")
    rm = build_world_mesh(suite.world, root / suite.world.mesh_config)
    E = pq.read_table(out / "episodes.parquet").to_pandas()
    visited = rm.crossings.point[E["target_id"].to_numpy()]
    np.testing.assert_allclose(visited[:, 0], 0.96, atol=1e-3)  # the front mat, facing the robot (-x)
    assert rm.layout.surface.normal(visited)[:, 0].max() < -0.999


TIE_COLUMNS = {
    "reason": "converged",
    "target_id": 5,
    "final_tilt_error_deg": 0.3,
    "final_jaw_error_deg": 0.2,
    "tied": True,
    "tcp_lateral_error_m": 0.0005,
    "tie_tilt_error_deg": 0.3,
    "tie_jaw_error_deg": 0.2,
    "tie_crossing_distance_m": 0.0006,
}


def test_check_fails_on_a_regression(tmp_path, root, monkeypatch, capsys):
    monkeypatch.chdir(root)
    run = tmp_path / "run"
    run.mkdir()
    rows = [
        {
            "mode": "ibvs",
            "converged": True,
            "iterations": 20,
            "final_error_px": 0.3,
            "final_true_error_px": 0.3,
            "final_true_lateral_error_m": 0.0004,
            "final_true_error_m": 0.0004,
            "tcp_reached": False,
            "tcp_error_m": float("nan"),
            "max_joint_position_ratio": 0.5,
            **TIE_COLUMNS,
        },
        {
            "mode": "pbvs",
            "converged": True,
            "iterations": 25,
            "final_error_px": 0.3,
            "final_true_error_px": 0.3,
            "final_true_lateral_error_m": 0.0004,
            "final_true_error_m": 0.0031,
            "tcp_reached": False,
            "tcp_error_m": float("nan"),
            "max_joint_position_ratio": 0.5,
            **TIE_COLUMNS,
        },
    ]
    import pyarrow as pa

    pq.write_table(pa.Table.from_pylist(rows), run / "episodes.parquet")
    (run / "summary.json").write_text(json.dumps({"suite": "ci"}))
    assert main(["servo", "check", str(run)]) == 1
    out = capsys.readouterr().out
    assert "REGRESSION ci pbvs: true_error_m" in out


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"detector": "yolo"}, ["detector", "yolo"]),
        ({"episodes": [], "random": None}, ["no episodes"]),
        ({"ibvs": {"gain": {"at_zero": 1.0, "at_infinity": 2.0, "slope_at_zero": 1.0}}}, ["at_infinity"]),
        ({"episods": []}, ["unknown key", "episods"]),
        (
            {"scene": {"surroundings": {"distractors": {"lower_layer_probability": 2}}}},
            ["lower_layer_probability"],
        ),
    ],
)
def test_bad_suites_are_one_clear_error(tmp_path, capsys, change, words):
    path = tmp_path / "bad.yaml"
    data = suite_dict()
    data.update(change)
    path.write_text(yaml.safe_dump(data))
    assert main(["servo", "run", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and all(w in err for w in words), err
    assert not (tmp_path / "o").exists()


def test_a_broken_episode_beyond_those_run_is_still_refused(tmp_path, capsys):
    episodes = suite_dict()["episodes"] + [{"mode": "visual", "targets": 1}]
    path = tmp_path / "suite.yaml"
    path.write_text(yaml.safe_dump(suite_dict(episodes=episodes)))
    out = tmp_path / "runs" / "o"
    assert main(["servo", "run", str(path), "--out", str(out), "--episodes", "1", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "episodes.1.mode = 'visual'" in err and "'ibvs' or 'pbvs'" in err, err
    assert not (tmp_path / "runs").exists()


def test_a_missing_model_writes_nothing_not_even_the_parent_of_out(tmp_path, root, capsys):
    suite = suite_dict(
        detector="shipped",
        detector_path=str(tmp_path / "nowhere.onnx"),
        world={"mesh_config": str(root / "pipelines/smoke.yaml")},
    )
    path = tmp_path / "suite.yaml"
    path.write_text(yaml.safe_dump(suite))
    out = tmp_path / "runs" / "o"
    assert main(["servo", "run", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "nowhere.onnx" in err, err
    assert not (tmp_path / "runs").exists()


def test_a_suite_pins_what_runs_the_shipped_detector(tmp_path, root, capsys):
    from rebar_data.perception.inference import detector as infer
    from rebar_data.servo.camera import kinect_intrinsics
    from rebar_data.servo.detectors import load_shipped_detector

    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    det = load_shipped_detector(None, kinect_intrinsics(), runtime="onnxruntime", reading="mirrored")
    assert det.inner.backend == "onnxruntime" and det.inner.reading == "mirrored"
    default = load_shipped_detector(None, kinect_intrinsics()).inner
    assert default.reading == "single" and not default.flatten_behind  # the servo's defaults
    assert load_shipped_detector(None, kinect_intrinsics(), flatten_behind=True).inner.flatten_behind
    path = tmp_path / "suite.yaml"
    path.write_text(yaml.safe_dump(suite_dict(detector="shipped", detector_runtime="tensorrt")))
    assert main(["servo", "run", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "detector_runtime" in err and "'onnxruntime'" in err, err
    assert not (tmp_path / "o").exists()
    path.write_text(yaml.safe_dump(suite_dict(detector="shipped", detector_reading="twice")))
    assert main(["servo", "run", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "detector_reading" in err and "'mirrored'" in err, err
    assert not (tmp_path / "o").exists()
