from __future__ import annotations

import hashlib

import numpy as np
import pytest

from rebar_data.geometry.build import build_rebar_mesh
from rebar_data.geometry.config import MeshConfig
from rebar_data.geometry.export import write_mesh_outputs
from rebar_data.geometry.specs import positions
from rebar_data.pipeline import load_mesh_config


def _cfg(**mesh) -> MeshConfig:
    base = {"kind": "planar", "width_m": 1.0, "height_m": 0.6, "spacing_x_m": 0.1, "spacing_y_m": 0.1}
    realism = mesh.pop("realism", {})
    return MeshConfig.model_validate({"seed": 3, "mesh": {**base, **mesh}, "realism": realism})


def _point_on_curve_error(curve, p):
    return np.linalg.norm(curve.point(curve.project(p)) - p)


@pytest.fixture(scope="module")
def paper(root):
    return build_rebar_mesh(load_mesh_config(root / "pipelines/paper-tunnel.yaml"))


def test_paper_crossing_count_is_what_the_spacing_implies(paper):
    m = paper.config.mesh
    n_hoops = len(positions(m.width_m, m.spacing_axial_m, m.end_cover_m, 0.0))
    lines = [b for b in paper.bars if b.direction == 1]
    hoops = [b for b in paper.bars if b.direction == 0]
    assert len(hoops) == n_hoops == 30
    assert len(lines) == 24  # arc length 0.7725 rad x 3.185 m = 2.46 m, 50 mm end cover, 100 mm spacing
    assert len(paper.crossings) == len(hoops) * len(lines) == 720


def test_paper_crossings_lie_on_both_centerlines_and_are_closest_points(paper):
    c = paper.crossings
    for k in range(len(c)):
        a, b = paper.bars[c.bar_a[k]].curve, paper.bars[c.bar_b[k]].curve
        assert _point_on_curve_error(a, c.point_a[k]) < 1e-9
        assert _point_on_curve_error(b, c.point_b[k]) < 1e-9
        d = c.point_b[k] - c.point_a[k]
        assert abs(np.dot(d, a.tangent(a.project(c.point_a[k])))) < 1e-9
        assert abs(np.dot(d, b.tangent(b.project(c.point_b[k])))) < 1e-9
    np.testing.assert_allclose(c.point, (c.point_a + c.point_b) / 2)
    np.testing.assert_allclose(c.gap_m, 0.0, atol=1e-9)  # the paper's bars touch


def test_tunnel_crossings_lie_on_the_arcs_cylinder(paper):
    m = paper.config.mesh
    axis_point = paper.layout.axis_point
    r = np.hypot(paper.crossings.point[:, 1] - axis_point[1], paper.crossings.point[:, 2] - axis_point[2])
    expected = m.extrados_radius_m - m.cover_m - m.bar_diameter_m
    np.testing.assert_allclose(r, expected, atol=1e-9)
    # normals are radial and unit length
    radial = paper.crossings.point - axis_point
    radial[:, 0] = 0
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    np.testing.assert_allclose(paper.crossings.normal, radial, atol=1e-12)


def test_merged_mesh_is_watertight_with_a_part_per_triangle(paper):
    assert paper.mesh.is_watertight
    assert len(paper.triangle_part_id) == len(paper.mesh.faces)
    assert set(np.unique(paper.triangle_bar_id)) == set(range(len(paper.bars)))
    for p in paper.parts[:5]:
        assert p.mesh.is_watertight and p.mesh.volume > 0


def test_planar_grid_and_two_layers_give_expected_counts():
    one = build_rebar_mesh(_cfg())
    # usable 0.9 x 0.5 m at 0.1 m: 10 bars along x (placed along y: 6), 6 x 10 = 60 crossings
    assert sum(b.direction == 0 for b in one.bars) == 6
    assert sum(b.direction == 1 for b in one.bars) == 10
    assert len(one.crossings) == 60
    two = build_rebar_mesh(_cfg(layers=[{"face": "top"}, {"face": "bottom", "offset_m": [0.05, 0.05]}]))
    assert len(two.crossings) == 60 + 5 * 9  # the offset bottom layer loses its last row and column
    assert set(np.unique(two.crossings.layer)) == {0, 1}
    # no crossing between layers: every crossing's bars share a layer
    layer_of = np.array([b.layer for b in two.bars])
    assert np.all(layer_of[two.crossings.bar_a] == layer_of[two.crossings.bar_b])


def test_realism_options_change_the_grid_as_asked():
    real = {
        "missing_fraction": 0.2,
        "diameters_m": [0.012, 0.016],
        "bow_m": 0.01,
        "jitter_m": 0.003,
        "tie_wire_fraction": 0.5,
        "ribs": True,
    }
    rm = build_rebar_mesh(_cfg(width_m=0.6, height_m=0.4, realism=real))
    assert len(rm.bars) < 6 + 4  # some bars are missing
    assert {b.diameter_m for b in rm.bars} <= {0.012, 0.016}
    assert any(b.curve.kind == "arc" for b in rm.bars)  # bowed straight bars are arcs
    assert any(p.kind == "tie_wire" for p in rm.parts)
    assert rm.mesh.is_watertight
    assert np.all(rm.crossings.gap_m <= rm.config.mesh.crossing_tolerance_m + 1e-12)


def test_realism_streams_are_independent():
    a = build_rebar_mesh(_cfg(realism={"jitter_m": 0.003}))
    b = build_rebar_mesh(_cfg(realism={"jitter_m": 0.003, "tie_wire_fraction": 0.5}))
    np.testing.assert_array_equal(a.crossings.point, b.crossings.point)


def test_same_seed_gives_byte_identical_outputs(tmp_path, root):
    cfg = load_mesh_config(root / "pipelines/smoke.yaml")
    digests = []
    for name in ("a", "b"):
        write_mesh_outputs(build_rebar_mesh(cfg), tmp_path / name)
        digests.append(
            {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted((tmp_path / name).iterdir())}
        )
    assert digests[0] == digests[1]
    assert set(digests[0]) >= {"mesh.glb", "mesh.ply", "bars.parquet", "crossings.parquet"}
    other = cfg.model_copy(update={"seed": cfg.seed + 1})
    write_mesh_outputs(build_rebar_mesh(other), tmp_path / "c")
    assert (
        hashlib.sha256((tmp_path / "c/crossings.parquet").read_bytes()).hexdigest()
        != digests[0]["crossings.parquet"]
    )


def test_mesh_pose_moves_everything_rigidly():
    base = build_rebar_mesh(_cfg())
    cfg = MeshConfig.model_validate(
        {**_cfg().model_dump(), "pose": {"translation_m": [1, 2, 3], "rotation_deg": [0, 0, 90]}}
    )
    moved = build_rebar_mesh(cfg)
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(moved.crossings.point, base.crossings.point @ R.T + [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(moved.crossings.normal, base.crossings.normal @ R.T, atol=1e-12)
