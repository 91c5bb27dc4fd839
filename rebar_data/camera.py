"""The pinhole camera of the whole package: intrinsics, the pose convention, projection, pixel rays and the
point feature's interaction matrix. The renderer, the labels, the dataset files, the detector and the servo
loop all read images through it.

Conventions, the same everywhere:

- Camera frame: OpenCV's axes, x right, y down, z forward along the optical axis; depth is camera z.
- Pose: ``world_from_camera``, a rigid 4x4 matrix that takes camera-frame points into the world: its columns
  are the camera's x, y and z axes and its centre, in world coordinates. Its :func:`rigid_inverse` is
  ``camera_from_world``; transforms chain right to left
  (``world_from_tool = world_from_camera @ camera_from_tool``).
- Pixels: COCO's corner origin. The pixel in row i, column j covers ``[j, j + 1) x [i, i + 1)`` and its centre
  is ``(j + 0.5, i + 0.5)``; a camera-frame point projects to ``u = fx * x / z + cx``, ``v = fy * y / z + cy``.
- Normalised image coordinates: ``(x, y) = ((u - cx) / fx, (v - cy) / fy)``; the ray through the pixel is
  ``(x, y, 1)`` in the camera frame.

Only numpy: the detector's run time reads its frames through this module too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels (COCO's corner origin: ``u = fx * x / z + cx``) and the image size."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fov_deg(self) -> tuple[float, float]:
        """The horizontal and vertical fields of view, degrees (a centred principal point)."""
        return (
            float(np.degrees(2 * np.arctan(self.width / 2 / self.fx))),
            float(np.degrees(2 * np.arctan(self.height / 2 / self.fy))),
        )

    @property
    def principal_point(self) -> np.ndarray:
        return np.array([self.cx, self.cy])

    def resized(self, width: int, height: int) -> Intrinsics:
        """The intrinsics of this camera's image resized to ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy)

    def mirrored(self) -> Intrinsics:
        """The intrinsics of this camera's image mirrored left to right (column u shows at ``width - u``)."""
        return Intrinsics(self.width, self.height, self.fx, self.fy, self.width - self.cx, self.cy)

    def project(self, points_camera: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of camera-frame points (N, 3); NaN behind the camera."""
        p = np.atleast_2d(points_camera)
        z = np.where(p[:, 2] > 0, p[:, 2], np.nan)
        return np.stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy], axis=1)

    def normalized(self, uv: np.ndarray) -> np.ndarray:
        """Normalised image coordinates (x/z, y/z) of pixels (N, 2)."""
        uv = np.atleast_2d(uv)
        return np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], axis=1)

    def back_project(self, uv: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) of pixels (N, 2) at metric z ``depth_m`` (N,)."""
        xy = self.normalized(uv)
        z = np.asarray(depth_m, float).reshape(-1)
        return np.stack([xy[:, 0] * z, xy[:, 1] * z, z], axis=1)

    def ray_grid(self, stride: int = 1) -> np.ndarray:
        """(2, ceil(H / stride), ceil(W / stride)) float64: the normalised image coordinates (x, y) of the
        centres of the image's ``stride`` x ``stride`` cells (stride 1: of its pixels)."""
        x = (stride * (np.arange(-(-self.width // stride), dtype=np.float64) + 0.5) - self.cx) / self.fx
        y = (stride * (np.arange(-(-self.height // stride), dtype=np.float64) + 0.5) - self.cy) / self.fy
        return np.stack(np.broadcast_arrays(x[None, :], y[:, None]))

    def pixel_rays(self, *, unit: bool = False) -> np.ndarray:
        """(H*W, 3) float64 rays through every pixel centre in the camera frame, row-major: (x, y, 1), or
        of unit length with ``unit``."""
        x, y = self.ray_grid().reshape(2, -1)
        d = np.stack([x, y, np.ones_like(x)], axis=1)
        return d / np.linalg.norm(d, axis=1, keepdims=True) if unit else d


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (``camera_from_world`` of ``world_from_camera``), without a general
    matrix inverse."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


@dataclass(frozen=True)
class Projection:
    """World points seen by a camera: in its frame, their pixels (NaN behind it), and ``in_image``: in front
    of the camera and inside the frame."""

    point_camera: np.ndarray  # (N, 3)
    u: np.ndarray
    v: np.ndarray
    in_image: np.ndarray  # bool (N,)

    @property
    def depth_m(self) -> np.ndarray:
        return self.point_camera[:, 2]


def project(points_world: np.ndarray, world_from_camera: np.ndarray, camera: Intrinsics) -> Projection:
    """The projection of world points (N, 3) by ``camera`` at ``world_from_camera``; the image spans
    ``[0, width) x [0, height)``."""
    T = rigid_inverse(world_from_camera)
    pc = points_world @ T[:3, :3].T + T[:3, 3]
    uv = camera.project(pc)
    u, v = uv[:, 0], uv[:, 1]
    with np.errstate(invalid="ignore"):
        inside = (pc[:, 2] > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    return Projection(pc, u, v, inside)


def point_interaction_matrix(x: float, y: float, Z: float) -> np.ndarray:
    """The 2x6 interaction matrix (image Jacobian) of an image point at normalised ``(x, y)`` and depth Z:
    ``d(x, y)/dt = L (v, w)`` for a still point, the twist (v, w) being the camera's, in the camera frame."""
    return np.array(
        [
            [-1.0 / Z, 0.0, x / Z, x * y, -(1.0 + x * x), y],
            [0.0, -1.0 / Z, y / Z, 1.0 + y * y, -x * y, -x],
        ]
    )
