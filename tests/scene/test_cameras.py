from __future__ import annotations

import numpy as np
import pytest

from rebar_data.scene.cameras import PRESETS, intrinsics_from_config, look_at, trajectory_poses
from rebar_data.scene.config import Approach, CameraConfig, OrbitArc, RandomLookAt, StraightPass
from rebar_data.scene.mat_surface import MatSurface

KINDS = [
    OrbitArc(kind="orbit_arc", frames=7),
    StraightPass(kind="straight_pass", frames=7, length_m=(0.2, 0.3), edge_margin_m=0.0),  # fits the piece
    Approach(kind="approach", frames=7),
    RandomLookAt(kind="random_look_at", frames=7),
]


def test_presets_and_explicit_intrinsics():
    k = intrinsics_from_config(CameraConfig(intrinsics="kinect_v1"))
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy) == (640, 480, 525.0, 525.0, 320.0, 240.0)
    assert np.allclose(k.K, [[525, 0, 320], [0, 525, 240], [0, 0, 1]])
    sq = PRESETS["square_640"]
    assert (sq.width, sq.height, sq.cx, sq.cy) == (640, 640, 320.0, 320.0)
    ex = intrinsics_from_config(
        CameraConfig(intrinsics={"width": 100, "height": 80, "fx": 90, "fy": 91, "cx": 50.5, "cy": 40})
    )
    assert (ex.width, ex.fy, ex.cx) == (100, 91.0, 50.5)


def test_look_at_is_an_opencv_camera():
    eye, target = np.array([0.3, -0.2, 1.0]), np.array([0.0, 0.1, 0.0])
    T = look_at(eye, target, np.array([1.0, 0.0, 0.0]), roll_rad=0.4)
    R = T[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    # the target is on the optical axis (+z) in front of the camera
    p_cam = R.T @ (target - eye)
    assert np.allclose(p_cam[:2], 0.0, atol=1e-12) and p_cam[2] > 0


def _axis_hit(surf: MatSurface, T: np.ndarray) -> float:
    """Distance along the optical axis to the mat surface (bisection on the height)."""
    eye, z = T[:3, 3], T[:3, 2]
    lo, hi = 0.0, 5.0
    assert surf.height(eye[None])[0] > 0 and surf.height((eye + hi * z)[None])[0] < 0
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if surf.height((eye + mid * z)[None])[0] > 0 else (lo, mid)
    return (lo + hi) / 2


@pytest.mark.parametrize("traj", KINDS, ids=lambda t: t.kind)
@pytest.mark.parametrize("mesh", ["tunnel_rm", "planar_rm"])
def test_poses_look_at_the_mat_from_outside_at_the_standoff(traj, mesh, request):
    rm = request.getfixturevalue(mesh)
    surf = MatSurface.of(rm)
    poses = trajectory_poses(traj, rm, np.random.default_rng(1))
    assert poses.shape == (7, 4, 4)
    lo, hi = surf.bounds()
    for T in poses:
        assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9)
        d = _axis_hit(surf, T)
        assert traj.standoff_m[0] - 1e-6 <= d <= traj.standoff_m[1] + 1e-6
        hit_ab = surf.to_ab((T[:3, 3] + d * T[:3, 2])[None])[0]
        assert np.all(hit_ab >= lo - 1e-6) and np.all(hit_ab <= hi + 1e-6)
        # tilt: angle between the optical axis and the inward normal at the hit
        n = surf.frame(hit_ab[None])[3][0]
        tilt = np.degrees(np.arccos(np.clip(-T[:3, 2] @ n, -1, 1)))
        assert traj.tilt_deg[0] - 1e-6 <= tilt <= traj.tilt_deg[1] + 1e-6


def test_trajectory_kinds_move_as_described(tunnel_rm):
    surf = MatSurface.of(tunnel_rm)
    rng = np.random.default_rng(2)
    app = trajectory_poses(Approach(kind="approach", frames=5, standoff_m=(0.4, 0.9)), tunnel_rm, rng)
    dists = [_axis_hit(surf, T) for T in app]
    assert np.allclose(dists, np.linspace(0.9, 0.4, 5), atol=1e-6)
    orbit = trajectory_poses(OrbitArc(kind="orbit_arc", frames=5, sweep_deg=(90, 90)), tunnel_rm, rng)
    dists = [_axis_hit(surf, T) for T in orbit]
    assert np.ptp(dists) < 1e-6  # one stand-off, one target
    targets = [T[:3, 3] + d * T[:3, 2] for T, d in zip(orbit, dists, strict=True)]
    assert np.ptp(np.array(targets), axis=0).max() < 1e-6
    sp = StraightPass(kind="straight_pass", frames=5, length_m=(0.4, 0.4), edge_margin_m=0.0)
    passing = trajectory_poses(sp, tunnel_rm, rng)
    hits = np.array([surf.to_ab((T[:3, 3] + _axis_hit(surf, T) * T[:3, 2])[None])[0] for T in passing])
    steps = np.linalg.norm(np.diff(hits, axis=0), axis=1)
    assert np.allclose(steps, 0.1, atol=1e-6)  # evenly along a 0.4 m line


def test_same_seed_same_poses(tunnel_rm):
    for traj in KINDS:
        a = trajectory_poses(traj, tunnel_rm, np.random.default_rng(9))
        b = trajectory_poses(traj, tunnel_rm, np.random.default_rng(9))
        c = trajectory_poses(traj, tunnel_rm, np.random.default_rng(10))
        assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_default_standoffs_show_tens_of_crossings_with_bars_several_px_wide(tunnel_rm):
    """On a 1.0 x 0.8 m piece the frame holds most of it; the bar width is what the defaults fix."""
    cam = CameraConfig()
    k = intrinsics_from_config(cam)
    counts, widths = [], []
    for traj in cam.trajectories:
        for T in trajectory_poses(traj, tunnel_rm, np.random.default_rng(0)):
            pc = (tunnel_rm.crossings.point - T[:3, 3]) @ T[:3, :3]
            u = k.fx * pc[:, 0] / pc[:, 2] + k.cx
            v = k.fy * pc[:, 1] / pc[:, 2] + k.cy
            inside = (pc[:, 2] > 0) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
            counts.append(inside.sum())
            widths.extend(k.fx * 0.012 / pc[inside, 2])
    assert np.median(counts) >= 10
    assert np.percentile(widths, 5) >= 5.0 and np.percentile(widths, 95) <= 20.0
