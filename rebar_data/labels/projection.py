"""The exact pinhole projection of world points (OpenCV camera axes, COCO pixel origin)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Projection:
    """Camera-frame points and their pixels; ``in_image`` is in front of the camera and inside the frame."""

    point_camera: np.ndarray  # (N, 3)
    u: np.ndarray
    v: np.ndarray
    in_image: np.ndarray  # bool (N,)

    @property
    def depth_m(self) -> np.ndarray:
        return self.point_camera[:, 2]


def camera_from_world(world_from_camera: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform, without a general matrix inverse."""
    R, t = world_from_camera[:3, :3], world_from_camera[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def project(
    points_world: np.ndarray,
    world_from_camera: np.ndarray,
    *,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
) -> Projection:
    """u = fx * x / z + cx, v = fy * y / z + cy; the image spans [0, width) x [0, height)."""
    T = camera_from_world(world_from_camera)
    pc = points_world @ T[:3, :3].T + T[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * pc[:, 0] / z + cx
        v = fy * pc[:, 1] / z + cy
    inside = (z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return Projection(pc, u, v, inside)
