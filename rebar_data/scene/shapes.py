"""Triangle meshes with per-corner texture coordinates for the surroundings and distractors.

A :class:`Shape` keeps vertices, triangles and one ``(u, v)`` per triangle corner (metres, to be divided
by a texture's size), so texture seams can be cut without duplicating geometry.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Shape:
    vertices: np.ndarray  # (V, 3) float64
    triangles: np.ndarray  # (T, 3) int32
    corner_uv_m: np.ndarray  # (T, 3, 2) float64, metres

    @staticmethod
    def concat(shapes: list[Shape]) -> Shape:
        if not shapes:
            return Shape(np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros((0, 3, 2)))
        offsets = np.cumsum([0] + [len(s.vertices) for s in shapes[:-1]])
        return Shape(
            np.concatenate([s.vertices for s in shapes]),
            np.concatenate([s.triangles + o for s, o in zip(shapes, offsets, strict=True)]).astype(np.int32),
            np.concatenate([s.corner_uv_m for s in shapes]),
        )


def grid(points: np.ndarray, uv_m: np.ndarray, *, flip: bool = False) -> Shape:
    """A quad grid through ``points`` (R, C, 3) with per-point texture coordinates ``uv_m`` (R, C, 2).

    Triangles face along (row direction) x (column direction), or the other way with ``flip``.
    """
    rows, cols = points.shape[:2]
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)]).astype(np.int32)
    if flip:
        tris = tris[:, [0, 2, 1]]
    uv = uv_m.reshape(-1, 2)
    return Shape(points.reshape(-1, 3).astype(float), tris, uv[tris])


def _frames(points: np.ndarray, up_hint: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tangents and two normals along a polyline, by parallel transport from ``up_hint``."""
    seg = np.diff(points, axis=0)
    t = np.concatenate([seg[:1], seg[:-1] + seg[1:], seg[-1:]])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    n1 = np.empty_like(t)
    ref = up_hint - np.dot(up_hint, t[0]) * t[0]
    if np.linalg.norm(ref) < 1e-6:
        ref = np.cross(t[0], [1.0, 0.0, 0.0] if abs(t[0, 0]) < 0.9 else [0.0, 1.0, 0.0])
    n1[0] = ref / np.linalg.norm(ref)
    for i in range(1, len(t)):
        v = n1[i - 1] - np.dot(n1[i - 1], t[i]) * t[i]
        n1[i] = v / np.linalg.norm(v)
    return t, n1, np.cross(t, n1)


def polyline_tube(points: np.ndarray, radius: float, *, up_hint: np.ndarray, sides: int = 10) -> Shape:
    """A capped tube along a polyline. ``u`` runs along it, ``v`` around it from ``up_hint`` (the seam
    is on the side opposite ``up_hint``)."""
    points = np.asarray(points, float)
    _, n1, n2 = _frames(points, up_hint)
    ang = np.linspace(-np.pi, np.pi, sides + 1)  # last column repeats the first, so the seam gets its own uv
    ring = np.cos(ang)[None, :, None] * n1[:, None, :] + np.sin(ang)[None, :, None] * n2[:, None, :]
    verts = points[:, None, :] + radius * ring
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    uv = np.stack(np.broadcast_arrays(s[:, None], (ang * radius)[None, :]), axis=-1)
    side = grid(verts, uv, flip=True)  # row x column points inwards on a tube
    caps = []
    for end, sign in ((0, -1.0), (len(points) - 1, 1.0)):
        rim = verts[end, :-1]
        centre = points[end]
        k = np.arange(sides)
        v = np.vstack([rim, centre])
        tris = np.stack([np.full(sides, sides), k, (k + 1) % sides], 1)
        if sign < 0:  # the start cap faces back along the tube
            tris = tris[:, [0, 2, 1]]
        local = (v - centre) @ np.stack([n1[end], n2[end]], 1)
        caps.append(Shape(v, tris.astype(np.int32), local[tris]))
    return Shape.concat([side, *caps])


def box(centre: np.ndarray, axes: np.ndarray, half: np.ndarray) -> Shape:
    """A box with unit ``axes`` (3 rows) and half extents ``half``; each face is mapped flat."""
    faces = []
    for k in range(3):
        i, j = (k + 1) % 3, (k + 2) % 3
        for sign in (-1.0, 1.0):
            corners = np.array([[-1, -1], [1, -1], [-1, 1], [1, 1]], float)
            pts = (
                centre
                + sign * half[k] * axes[k]
                + corners[:, :1] * half[i] * axes[i]
                + corners[:, 1:] * half[j] * axes[j]
            )
            uv = corners * np.array([half[i], half[j]])
            tris = (
                np.array([[0, 1, 3], [0, 3, 2]], np.int32) if sign > 0 else np.array([[0, 3, 1], [0, 2, 3]])
            )
            faces.append(Shape(pts, tris.astype(np.int32), uv[tris]))
    return Shape.concat(faces)


def cylinder(base: np.ndarray, axis: np.ndarray, radius: float, height: float, *, sides: int = 16) -> Shape:
    """A closed cylinder standing on ``base`` along unit ``axis``."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return polyline_tube(
        np.stack([base, base + height * axis]), radius, up_hint=_any_square(axis), sides=sides
    )


def _any_square(v: np.ndarray) -> np.ndarray:
    h = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    w = np.cross(v, h)
    return w / np.linalg.norm(w)
