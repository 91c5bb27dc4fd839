"""Tours: the crossing map, the path over it, and a short tour through the whole loop."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

from rebar_data.cli import main
from rebar_data.servo.tour import FAILED, LOWER, OPEN, CrossingMap, MapEntry, open_path
from tests.servo.conftest import suite_dict


def _length(start, points, order):
    path = np.vstack([start[None], points[order]])
    return float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))


def test_the_path_visits_each_point_once_and_2opt_never_lengthens_it():
    rng = np.random.default_rng(4)
    pts = rng.uniform(-1, 1, (12, 3))
    start = np.zeros(3)
    order = open_path(start, pts)
    assert sorted(order.tolist()) == list(range(12))
    # nearest neighbour alone, for comparison
    left, here, nn = list(range(12)), start, []
    while left:
        j = min(left, key=lambda i: np.linalg.norm(pts[i] - here))
        nn.append(j)
        left.remove(j)
        here = pts[j]
    assert _length(start, pts, order) <= _length(start, pts, np.array(nn)) + 1e-12
    line = np.array([[3.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    assert open_path(np.zeros(3), line).tolist() == [1, 2, 0]
    assert open_path(np.zeros(3), np.zeros((0, 3))).tolist() == []


def test_the_map_merges_sightings_and_keeps_the_lower_mat_apart():
    m = CrossingMap(0.03)
    a = m.add(np.array([0.0, 0.0, 0.0]), lower=False)
    b = m.add(np.array([0.01, 0.0, 0.0]), lower=False)
    assert a is b and a.sightings == 2 and a.point[0] == pytest.approx(0.005)
    c = m.add(np.array([0.1, 0.0, 0.0]), lower=True)
    assert c is not a and c.state == LOWER and a.state == OPEN
    assert m.count(OPEN) == 1 and m.count(LOWER) == 1


def test_a_base_leaves_a_crossing_it_cannot_tie_and_a_later_base_tries_it_again():
    e = MapEntry(point=np.zeros(3), sightings=1)
    e.failed(base=0, max_attempts=2)
    assert e.state == OPEN and e.open_to(0)  # one more try from here
    e.failed(base=0, max_attempts=2)
    assert e.state == FAILED and not e.open_to(0) and e.open_to(1)
    e.here = 0  # the next base's tries are its own
    e.failed(base=1, max_attempts=2, out_of_reach=True)  # the tool did not reach its tie pose: left at once
    assert not e.open_to(1) and e.open_to(2) and e.attempts == 3 and e.left_by == {0, 1}


def test_a_short_tour_ties_each_crossing_once_square_and_on_time(tmp_path, root, monkeypatch, capsys):
    monkeypatch.chdir(root)
    suite = suite_dict(name="tour-test", episodes=[], tour={"mode": "ibvs", "max_ties": 4})
    path = tmp_path / "tour.yaml"
    path.write_text(yaml.safe_dump(suite))
    out = tmp_path / "run"
    assert main(["servo", "run", str(path), "--out", str(out), "--quiet"]) == 0
    E = pq.read_table(out / "episodes.parquet").to_pandas()
    tied = E[E["tied"]]
    assert len(tied) == 4 and tied["target_id"].is_unique and (tied["target_id"] >= 0).all()
    assert (tied["tcp_lateral_error_m"] < 0.002).all() and (tied["tie_crossing_distance_m"] < 0.005).all()
    assert (tied["tie_tilt_error_deg"] < 2.0).all() and (tied["tie_jaw_error_deg"] < 5.0).all()
    # the path runs between neighbours: each tie after the first is on a crossing next to the one before
    from rebar_data.servo.config import SuiteConfig
    from rebar_data.servo.world import build_world_mesh

    rm = build_world_mesh(SuiteConfig.model_validate(suite).world, root / "pipelines" / "paper-tunnel.yaml")
    p = rm.crossings.point[tied["target_id"].to_numpy()]
    assert (np.linalg.norm(np.diff(p, axis=0), axis=1) < 0.15).all()  # 100 mm spacing; a diagonal is 141 mm
    tour = json.loads((out / "summary.json").read_text())["tour"]
    assert tour["ties"] == 4 and tour["crossings_tied"] == 4 and tour["ties_off_crossings"] == 0
    assert tour["map"]["tied"] == 4 and tour["map"]["open"] > 0
    assert 2.0 < tour["sim_s_per_tie"] < 4.5  # 1.0 s of dwell in each
    S = pq.read_table(out / "steps.parquet").to_pandas()
    assert {"servo", "approach", "tie", "retract"} <= set(S["phase"])
    thresholds = tmp_path / "bars.yaml"
    thresholds.write_text(
        yaml.safe_dump(
            {
                "suites": {
                    "tour-test": {
                        "ibvs": {"min_visits": 4, "min_tied_fraction": 0.99, "max_sim_s_per_tie": 4.5},
                        "pbvs": {"min_visits": 0},
                    }
                }
            }
        )
    )
    capsys.readouterr()
    assert main(["servo", "check", str(out), "--thresholds", str(thresholds)]) == 0, capsys.readouterr().out
    thresholds.write_text(
        yaml.safe_dump(
            {"suites": {"tour-test": {"ibvs": {"max_sim_s_per_tie": 1.0, "max_tilt_error_deg": 0.01}}}}
        )
    )
    assert main(["servo", "check", str(out), "--thresholds", str(thresholds)]) == 1
    text = capsys.readouterr().out
    assert "sim_s_per_tie" in text and "tilt_error_deg" in text
