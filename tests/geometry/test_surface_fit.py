"""The surface fitted to a mesh read from IFC, its camera side and its mats: on the sample wall (a vertical
plane, turned and moved off the origin, two mats, stirrups and U-bars) and on a tunnel segment written to IFC
(a cylinder); overrides and bad values."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("ifcopenshell")

from rebar_data.cli import main  # noqa: E402
from rebar_data.config import ConfigError  # noqa: E402
from rebar_data.geometry.build import build_rebar_mesh  # noqa: E402
from rebar_data.geometry.ifc_samples import WALL_YAW_DEG, world_from_wall, write_wall  # noqa: E402
from rebar_data.geometry.ifc_write import write_ifc  # noqa: E402
from rebar_data.pipeline import load_mesh_config  # noqa: E402
from rebar_data.scene.cameras import trajectory_poses  # noqa: E402
from rebar_data.scene.config import OrbitArc, RandomLookAt  # noqa: E402
from rebar_data.scene.mat_surface import MatSurface  # noqa: E402
from tests.ifc_models import ROOT, pipeline, read_mesh  # noqa: E402

WALL_FRONT = world_from_wall()[:3, 1]  # the wall's +y face: (0.866, 0.5, 0) after its -60 degree turn


@pytest.fixture(scope="module")
def wall_bytes(tmp_path_factory) -> bytes:
    return write_wall(tmp_path_factory.mktemp("wall") / "wall.ifc").read_bytes()


@pytest.fixture
def wall(wall_bytes, tmp_path):
    """The sample wall, written beside the test's pipeline files."""
    path = tmp_path / "wall.ifc"
    path.write_bytes(wall_bytes)
    return path


def test_the_wall_is_a_plane_seen_from_plus_x_and_its_top_mat_is_the_front_mat(wall, tmp_path):
    rm = read_mesh(tmp_path, wall, crossings="top_mat")
    fit = rm.layout.surface
    assert fit.kind == "plane" and WALL_YAW_DEG == -60.0
    np.testing.assert_allclose(fit.world_from_surface[:3, 2], WALL_FRONT, atol=1e-9)  # +x side of a wall
    assert fit.camera_side.startswith("+x")
    # two mats 0.1164 m apart (mid-layers at +-0.0582), the plane through the middle: rms = max = 0.058..0.065
    assert fit.plane_rms_m == pytest.approx(0.0575, abs=5e-4) and fit.plane_max_m == pytest.approx(
        0.0649, abs=1e-4
    )
    assert fit.cylinder_rms_m > fit.plane_rms_m  # auto keeps the plane
    assert [m.pieces for m in fit.mats] == [26, 26]  # 7 + 10 mat bars, 3 U-bar legs, 6 stirrup legs a face
    assert fit.mats[0].height_m == pytest.approx(0.0582, abs=1e-4) and fit.mats[1].height_m < 0
    assert int((fit.piece_mat < 0).sum()) == 45  # the stirrups' bends and cross legs, the U-bars' tops
    c = rm.crossings
    # 7 x 10 mat crossings, 3 U-bar legs x 3 horizontal bars, 6 stirrup legs x the middle vertical bar
    assert len(c) == 85 and set(c.layer.tolist()) == {0}
    assert np.all(fit.height(c.point) > 0.05) and np.all(c.normal @ WALL_FRONT > 0.999)
    assert np.all((c.point - world_from_wall()[:3, 3]) @ WALL_FRONT > 0)
    everything = read_mesh(tmp_path, wall)  # crossings: all
    assert len(everything.crossings) == 194 and -1 in everything.crossings.layer
    # cameras still face the top mat: the surface they stand off from passes through its crossings
    c = everything.crossings
    assert np.abs(MatSurface.of(everything).height(c.point[c.layer == 0])).max() < 1e-3


def test_cameras_look_at_the_wall_from_its_camera_side(wall, tmp_path):
    rm = read_mesh(tmp_path, wall, crossings="top_mat")
    surf = MatSurface.of(rm)
    rng = np.random.default_rng(0)
    for traj in (
        RandomLookAt(kind="random_look_at", count=1, frames=20),
        OrbitArc(kind="orbit_arc", count=1),
    ):
        poses = trajectory_poses(traj, rm, rng)
        eye, forward = poses[:, :3, 3], poses[:, :3, 2]
        assert np.all(surf.height(eye) > 0.3)  # stand-off from the front mat, not above the wall's top
        assert np.all(forward @ WALL_FRONT < -0.5)  # looking into the wall
        # the look-at points are on the wall: between its ends and between its base and top
        target = eye + forward * (surf.height(eye) / -(forward @ WALL_FRONT))[:, None]
        local = (target - world_from_wall()[:3, 3]) @ world_from_wall()[:3, :3]
        assert np.all(np.abs(local[:, 0]) < 0.8) and np.all((local[:, 2] > 0) & (local[:, 2] < 1.2))


def test_camera_side_and_top_mat_overrides_pick_the_back_mat(wall, tmp_path):
    front = read_mesh(tmp_path, wall, crossings="top_mat")
    back = read_mesh(tmp_path, wall, crossings="top_mat", camera_side=[-1.0, 0.0, 0.0])
    second = read_mesh(tmp_path, wall, crossings="top_mat", top_mat=1)
    np.testing.assert_allclose(back.layout.surface.world_from_surface[:3, 2], -WALL_FRONT, atol=1e-9)
    assert back.layout.surface.camera_side == "mesh.camera_side [-1.0, 0.0, 0.0]"
    assert len(back.crossings) == len(second.crossings) == 85
    np.testing.assert_allclose(back.crossings.point, second.crossings.point, atol=1e-12)
    assert np.all((back.crossings.point - world_from_wall()[:3, 3]) @ WALL_FRONT < 0)
    # mirrored through the wall's middle plane, the back mat's crossings are the front mat's
    mirrored = back.crossings.point - 2 * np.outer(
        (back.crossings.point - world_from_wall()[:3, 3]) @ WALL_FRONT, WALL_FRONT
    )
    key = lambda p: np.lexsort(np.round(p, 6).T)  # noqa: E731
    np.testing.assert_allclose(
        mirrored[key(mirrored)], front.crossings.point[key(front.crossings.point)], atol=1e-9
    )


def test_a_tunnel_segment_read_from_ifc_is_a_cylinder_seen_from_outside_or_inside(tmp_path):
    ifc = tmp_path / "smoke.ifc"
    source = build_rebar_mesh(load_mesh_config(ROOT / "pipelines/smoke.yaml"))
    write_ifc(source, ifc)
    rm = read_mesh(tmp_path, ifc)
    fit = rm.layout.surface
    assert fit.kind == "cylinder" and fit.side == 1 and fit.camera_side == "the cylinder's outside"
    # the cylinder's residuals are the mat's own thickness (two bar directions 12 mm apart in height); the
    # plane's add the arc's sagitta, and 10 hoops span more than 12 mm above it
    assert fit.cylinder_max_m < 0.007 and fit.cylinder_rms_m < fit.plane_rms_m and fit.plane_max_m > 0.017
    assert int((read_mesh(tmp_path, ifc, surface="plane").layout.surface.piece_mat < 0).sum()) == 10
    np.testing.assert_allclose(abs(fit.world_from_surface[:3, 0] @ [1.0, 0.0, 0.0]), 1.0, atol=1e-6, rtol=0)
    assert len(rm.crossings) == len(source.crossings) and len(fit.mats) == 1
    # a 0.8 m arc of a 3.2 m radius leaves the radius loosely fixed (3.04 m fitted to bars at 3.16 m), the
    # normals closely: within 0.26 degrees of the segment's at every crossing
    assert abs(fit.radius_m - 3.16) < 0.2 and np.all(np.abs(fit.height(rm.crossings.point)) < 1e-3)
    cos = np.sum(rm.layout.outward_normal(rm.crossings.point) * source.crossings.normal, axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 0.5
    # seen from inside: heights grow towards the axis, and the cameras stand inside the segment
    inside = read_mesh(tmp_path, ifc, camera_side=[0.0, 0.0, -1.0])
    assert inside.layout.surface.side == -1
    poses = trajectory_poses(
        RandomLookAt(kind="random_look_at", count=1, frames=10), inside, np.random.default_rng(1)
    )
    T = inside.layout.surface.world_from_surface
    radial = np.linalg.norm(((poses[:, :3, 3] - T[:3, 3]) @ T[:3, :3])[:, 1:], axis=1)
    assert np.all(radial < inside.layout.surface.radius_m - 0.3)
    assert read_mesh(tmp_path, ifc, surface="plane").layout.surface.kind == "plane"


@pytest.mark.parametrize(
    "mesh, words",
    [
        ({"camera_side": [0.0, 0.0, 0.0]}, ["camera_side = [0.0, 0.0, 0.0]", "non-zero"]),
        ({"camera_side": [0.0, 0.0, 1.0]}, ["mesh.camera_side = [0.0, 0.0, 1.0] lies in the fitted plane"]),
        ({"top_mat": 2}, ["mesh.top_mat = 2", "2 mats", "accepted: 0 to 1"]),
        ({"mat_gap_m": 0.0}, ["mesh.mat_gap_m = 0.0"]),
        ({"crossings": "lower"}, ["mesh.crossings = 'lower'"]),
        ({"surface": "cone"}, ["mesh.surface = 'cone'"]),
    ],
    ids=[
        "zero camera side",
        "camera side in the plane",
        "top mat past the last",
        "zero gap",
        "crossings",
        "surface",
    ],
)
def test_bad_surface_settings_are_one_line_exit_2(mesh, words, wall, tmp_path, capsys):
    cfg = pipeline(tmp_path, {"kind": "ifc", "ifc_path": "wall.ifc", **mesh})
    code = main(["mesh", str(cfg), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert all(w in err for w in words), err
    assert not (tmp_path / "out").exists()


def test_the_shipped_wall_is_what_the_generator_writes(wall, tmp_path):
    shipped = build_rebar_mesh(load_mesh_config(ROOT / "pipelines/ifc-wall.yaml"))
    fresh = read_mesh(tmp_path, wall, crossings="top_mat")
    assert len(shipped.bars) == len(fresh.bars) == 97 and len(shipped.crossings) == 85
    np.testing.assert_array_equal(shipped.crossings.point, fresh.crossings.point)
    for a, b in zip(shipped.bars, fresh.bars, strict=True):
        assert a.bar_id == b.bar_id and a.diameter_m == b.diameter_m and a.curve.kind == b.curve.kind


def test_a_surface_without_side_to_look_from_is_refused():
    from rebar_data.geometry.curves import Line
    from rebar_data.geometry.surface_fit import fit_surface

    with pytest.raises(ConfigError, match="too few to fit one"):
        fit_surface([Line(np.zeros(3), np.array([0.01, 0.0, 0.0]))], np.array([0.01]), surface="cylinder")


def test_the_camera_side_is_the_models_and_moves_with_its_pose(wall, tmp_path):
    """A pose that turns the wall's front to -x keeps the front mat on top: the side is chosen in the model's
    frame (a servo world places the model by its own pose)."""
    still = read_mesh(tmp_path, wall, crossings="top_mat")
    pose = {"rotation_deg": [0.0, 0.0, 150.0], "translation_m": [1.0, 2.0, 3.0]}
    cfg = pipeline(tmp_path, {"kind": "ifc", "ifc_path": "wall.ifc", "crossings": "top_mat"}, pose=pose)
    moved = build_rebar_mesh(load_mesh_config(cfg))
    c, s = np.cos(np.radians(150.0)), np.sin(np.radians(150.0))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(
        moved.crossings.point, still.crossings.point @ R.T + [1.0, 2.0, 3.0], atol=1e-9
    )
    np.testing.assert_allclose(moved.layout.surface.world_from_surface[:3, 2], R @ WALL_FRONT, atol=1e-9)


SHAFT = {"half_m": 1.0, "storey_m": 1.2, "spacing_m": 0.3}  # a small lift shaft: 2 m square, 1.2 m high
OUTER_MAT_M = 1.0 - 0.03 - 0.006  # the outer loops' axes from the shaft's axis


@pytest.fixture
def shaft(tmp_path):
    from rebar_data.geometry.ifc_samples import write_shaft

    return write_shaft(tmp_path / "shaft.ifc", **SHAFT)


def test_a_cage_is_split_into_its_faces_each_seen_from_outside(shaft, tmp_path):
    """Four walls of two mats round a core: four vertical planes, each with its two mats, facing away from the
    core; the top mat is the chosen wall's outer mat, and cameras stand outside that wall."""
    rm = read_mesh(tmp_path, shaft, crossings="top_mat")
    faces = rm.layout.faces
    normals = sorted(np.round(f.world_from_surface[:3, 2], 2).tolist() for f in faces.fits)
    assert normals == [[-1, 0, 0], [0, -1, 0], [0, 1, 0], [1, 0, 0]]
    assert all(f.kind == "plane" and len(f.mats) == 2 for f in faces.fits)
    n = rm.layout.surface.world_from_surface[:3, 2]
    c = rm.crossings
    # the outer mat of one wall: its 4 loops' legs by its 6 vertical bars
    assert len(c) == 24 and np.all(c.point @ n > OUTER_MAT_M - 0.02)
    assert np.all(c.normal @ n > 0.999)
    rng = np.random.default_rng(0)
    poses = trajectory_poses(RandomLookAt(kind="random_look_at", count=1, frames=10), rm, rng)
    assert np.all(poses[:, :3, 3] @ n > 1.2) and np.all(poses[:, :3, 2] @ n < -0.5)  # outside, looking in


def test_a_box_round_one_wall_of_a_cage_faces_that_wall(shaft, tmp_path):
    """mesh.bbox_m round the +x wall keeps it whole with the loops through it: the wall is the face cameras
    face (a vertical plane), not a horizontal plane through the loops."""
    rm = read_mesh(tmp_path, shaft, crossings="top_mat", bbox_m=[[0.7, -1.1, 0.0], [1.1, 1.1, 1.2]])
    fit = rm.layout.surface
    np.testing.assert_allclose(fit.world_from_surface[:3, 2], [1.0, 0.0, 0.0], atol=1e-3)
    assert "mesh.bbox_m" in rm.layout.faces.how and [m.pieces for m in fit.mats][:1] == [4 + 6]
    assert len(rm.crossings) == 24 and np.all(rm.crossings.point[:, 0] > OUTER_MAT_M - 0.02)


def test_camera_side_picks_the_face_of_a_cage(shaft, tmp_path):
    rm = read_mesh(tmp_path, shaft, crossings="top_mat", camera_side=[0.0, -1.0, 0.0])
    np.testing.assert_allclose(rm.layout.surface.world_from_surface[:3, 2], [0.0, -1.0, 0.0], atol=1e-3)
    assert np.all(rm.crossings.point[:, 1] < -(OUTER_MAT_M - 0.02)) and len(rm.crossings) == 24
