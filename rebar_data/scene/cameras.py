"""The pipeline's camera: its intrinsics (presets or explicit) and its trajectories over the mat.

Poses are ``world_from_camera`` 4x4 matrices with OpenCV camera axes (x right, y down, z forward), the
convention of :mod:`rebar_data.camera`. Every trajectory looks at points of the mat from its outward side;
``standoff_m`` is the distance from the camera to the point it looks at, ``tilt_deg`` the angle between the
optical axis and the mat's inward normal there.
"""

from __future__ import annotations

import numpy as np

from rebar_data.camera import Intrinsics
from rebar_data.geometry.build import RebarMesh
from rebar_data.scene.config import (
    Approach,
    CameraConfig,
    ExplicitIntrinsics,
    OrbitArc,
    RandomLookAt,
    StraightPass,
    TrajectoryBase,
)
from rebar_data.scene.mat_surface import MatSurface

# Kinect v1 colour camera's common default calibration (cx, cy = 319.5, 239.5 in OpenCV's pixel-centre
# convention). RealSense D435 colour at 640x480 (69 x 42 degree sensor cropped to 4:3): fx = fy ~ 615.
# square_640 keeps Kinect's focal length, so pixels see the same angle, on the square frame detectors use.
PRESETS: dict[str, Intrinsics] = {
    "kinect_v1": Intrinsics(640, 480, 525.0, 525.0, 320.0, 240.0),
    "realsense_color": Intrinsics(640, 480, 615.0, 615.0, 320.0, 240.0),
    "square_640": Intrinsics(640, 640, 525.0, 525.0, 320.0, 320.0),
}


def intrinsics_from_config(cam: CameraConfig) -> Intrinsics:
    """The camera section's intrinsics: a preset by name or the explicit values."""
    k = cam.intrinsics
    if isinstance(k, ExplicitIntrinsics):
        return Intrinsics(k.width, k.height, k.fx, k.fy, k.cx, k.cy)
    return PRESETS[k]


def look_at(eye: np.ndarray, target: np.ndarray, right_hint: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """``world_from_camera`` at ``eye`` looking at ``target``; the image's x axis follows ``right_hint``
    (projected square to the view direction), then turned by ``roll_rad`` about the optical axis."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = right_hint - np.dot(right_hint, z) * z
    if np.linalg.norm(x) < 1e-6:  # hint along the view: any square direction will do
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    x, y = c * x + s * y, -s * x + c * y
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def _uniform(rng: np.random.Generator, r: tuple[float, float]) -> float:
    return float(rng.uniform(r[0], r[1])) if r[1] > r[0] else float(r[0])


def _pose_at(
    surf: MatSurface, ab: np.ndarray, *, standoff: float, tilt: float, azimuth: float, roll: float
) -> np.ndarray:
    """Camera looking at surface point ``ab`` from ``standoff`` metres, tilted by ``tilt`` (radians) from
    the normal towards ``azimuth`` (radians from the a axis)."""
    p, t_a, t_b, n = (x[0] for x in surf.frame(ab))
    offset = np.cos(tilt) * n + np.sin(tilt) * (np.cos(azimuth) * t_a + np.sin(azimuth) * t_b)
    return look_at(p + standoff * offset, p, t_a, roll)


def _target(surf: MatSurface, tcfg: TrajectoryBase, rng: np.random.Generator) -> np.ndarray:
    lo, hi = surf.bounds(tcfg.edge_margin_m)
    return np.array([_uniform(rng, (lo[0], hi[0])), _uniform(rng, (lo[1], hi[1]))])


def trajectory_poses(traj: TrajectoryBase, rm: RebarMesh, rng: np.random.Generator) -> np.ndarray:
    """One instance of a camera trajectory over the mat: ``(traj.frames, 4, 4)`` world_from_camera poses.

    All randomness (target, tilt, azimuth, roll, stand-off, sweep, path) comes from ``rng``.
    """
    surf = MatSurface.of(rm)
    n = traj.frames
    frac = np.linspace(0.0, 1.0, n) if n > 1 else np.zeros(1)
    deg = np.radians
    if isinstance(traj, RandomLookAt):
        poses = []
        for _ in range(n):
            ab = _target(surf, traj, rng)
            poses.append(
                _pose_at(
                    surf,
                    ab,
                    standoff=_uniform(rng, traj.standoff_m),
                    tilt=deg(_uniform(rng, traj.tilt_deg)),
                    azimuth=float(rng.uniform(0.0, 2.0 * np.pi)),
                    roll=deg(_uniform(rng, traj.roll_deg)),
                )
            )
        return np.stack(poses)
    tilt = deg(_uniform(rng, traj.tilt_deg))
    azimuth = float(rng.uniform(0.0, 2.0 * np.pi))
    roll = deg(_uniform(rng, traj.roll_deg))
    if isinstance(traj, OrbitArc):
        ab = _target(surf, traj, rng)
        standoff = _uniform(rng, traj.standoff_m)
        sweep = deg(_uniform(rng, traj.sweep_deg)) * (1.0 if rng.random() < 0.5 else -1.0)
        return np.stack(
            [
                _pose_at(surf, ab, standoff=standoff, tilt=tilt, azimuth=azimuth + sweep * f, roll=roll)
                for f in frac
            ]
        )
    if isinstance(traj, StraightPass):
        standoff = _uniform(rng, traj.standoff_m)
        length = _uniform(rng, traj.length_m)
        heading = float(rng.uniform(0.0, 2.0 * np.pi))
        direction = np.array([np.cos(heading), np.sin(heading)])
        # the pass stays over the mat: no longer than the crossings' extent along its heading
        full_lo, full_hi = surf.bounds()
        with np.errstate(divide="ignore"):
            fits = float(np.min((full_hi - full_lo) / np.abs(direction)))
        step = min(length, fits) * direction
        lo, hi = surf.bounds(traj.edge_margin_m)
        half = np.abs(step) / 2.0
        mid_lo, mid_hi = np.minimum(lo + half, (lo + hi) / 2.0), np.maximum(hi - half, (lo + hi) / 2.0)
        mid = np.array([_uniform(rng, (mid_lo[0], mid_hi[0])), _uniform(rng, (mid_lo[1], mid_hi[1]))])
        return np.stack(
            [
                _pose_at(
                    surf, mid + (f - 0.5) * step, standoff=standoff, tilt=tilt, azimuth=azimuth, roll=roll
                )
                for f in frac
            ]
        )
    if isinstance(traj, Approach):
        ab = _target(surf, traj, rng)
        far, near = traj.standoff_m[1], traj.standoff_m[0]
        return np.stack(
            [
                _pose_at(surf, ab, standoff=far + (near - far) * f, tilt=tilt, azimuth=azimuth, roll=roll)
                for f in frac
            ]
        )
    raise TypeError(f"unknown trajectory config {type(traj).__name__}")
