"""Small rigid-transform helpers (4x4 matrices, rotation vectors) shared by the servo modules; the inverse of
a rigid transform is :func:`rebar_data.camera.rigid_inverse`."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def make_transform(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


def translation(t) -> np.ndarray:
    return make_transform(t=np.asarray(t, float))


def rotvec(R: np.ndarray) -> np.ndarray:
    """Axis times angle of a rotation matrix."""
    return Rotation.from_matrix(R).as_rotvec()


def from_rotvec(w: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(w, float)).as_matrix()


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Transform points (N, 3) or (3,) by a 4x4 matrix."""
    p = np.asarray(points, float)
    return p @ T[:3, :3].T + T[:3, 3]
