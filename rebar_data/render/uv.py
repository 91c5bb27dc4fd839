"""Texture coordinates for the bars of a rebar mesh, which has none of its own.

Each bar part's vertices get ``u`` = arc length along the bar's centerline and ``v`` = arc length around
it, measured from the mat's outward side, so the texture's seam lies on the hidden inner side. Both are
in metres; callers divide by the texture tile's size. Each bar is offset into the tile differently, so
no two bars show the same patch of rust.
"""

from __future__ import annotations

import numpy as np

from rebar_data.geometry.build import RebarMesh
from rebar_data.geometry.curves import Arc, Curve, Line

_GOLDEN = 0.6180339887498949


def arc_length(curve: Curve, points: np.ndarray) -> np.ndarray:
    """Arc length ``s`` of the foot of each point on ``curve`` (vectorised ``curve.project``)."""
    if isinstance(curve, Line):
        return np.clip((points - curve.start) @ curve.direction, 0.0, curve.length)
    assert isinstance(curve, Arc)
    v = points - curve.center
    phi = np.arctan2(v @ curve.e2, v @ curve.e1) % (2.0 * np.pi)
    beyond = phi > curve.sweep
    nearer_end = (phi - curve.sweep) < (2.0 * np.pi - phi)
    phi = np.where(beyond, np.where(nearer_end, curve.sweep, 0.0), phi)
    return phi * curve.radius


def _piece_of(rm: RebarMesh, part_index: int) -> int:
    """The piece in ``rm.bars`` a bar part is swept along: the part's own (the first parts are the pieces'
    tubes, in order), or for a ball at a joint of a bar's pieces the piece of that bar nearest it."""
    part = rm.parts[part_index]
    if part_index < len(rm.bars) and rm.bars[part_index].bar_id == part.bar_id:
        return part_index
    centre = np.asarray(part.mesh.vertices).mean(0)
    pieces = [i for i, b in enumerate(rm.bars) if b.bar_id == part.bar_id]
    return min(
        pieces,
        key=lambda i: np.linalg.norm(rm.bars[i].curve.point(rm.bars[i].curve.project(centre)) - centre),
    )


def bar_corner_uv_m(rm: RebarMesh, part_index: int) -> np.ndarray:
    """Per-corner ``(u, v)`` in metres (T, 3, 2) for the triangles of bar part ``part_index``."""
    part = rm.parts[part_index]
    bar = rm.bars[_piece_of(rm, part_index)]
    verts = np.asarray(part.mesh.vertices)
    faces = np.asarray(part.mesh.faces)
    s = arc_length(bar.curve, verts)
    centre = bar.curve.point(s)
    tangent = bar.curve.tangent(s)
    outward = rm.layout.outward_normal(centre)
    ref = outward - np.sum(outward * tangent, axis=1, keepdims=True) * tangent
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    side = np.cross(tangent, ref)
    radial = verts - centre
    angle = np.arctan2(np.sum(radial * side, 1), np.sum(radial * ref, 1))  # 0 faces outwards
    corner_angle = angle[faces]
    # a triangle across the seam (angle jumps by ~2 pi) gets its negative corners unwrapped
    spans = corner_angle.max(1) - corner_angle.min(1)
    wrap = (spans > np.pi)[:, None] & (corner_angle < 0)
    corner_angle = np.where(wrap, corner_angle + 2.0 * np.pi, corner_angle)
    u = s[faces] + ((part.part_id * _GOLDEN) % 1.0) * 7.0
    v = corner_angle * bar.radius_m + ((part.part_id * _GOLDEN * _GOLDEN) % 1.0) * 7.0
    return np.stack([u, v], axis=-1)
