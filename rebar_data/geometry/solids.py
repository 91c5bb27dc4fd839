"""Watertight solids for bars and tie wire (manifold3d), merged with the part id kept per triangle.

Each bar is a circular tube swept along its centerline (optionally with transverse ribs, as a radius
profile), closed by end caps, and handed to manifold3d, which checks it is a valid solid. Tie wire is a
thin torus looped around both bars of a crossing. The union of all parts is one watertight mesh;
manifold3d's per-triangle provenance (``run_original_id``) gives each triangle's part, so later stages
can render exact instance ids.
"""

from __future__ import annotations

from dataclasses import dataclass

import manifold3d as mf
import numpy as np
import trimesh

from rebar_data.geometry.config import Realism
from rebar_data.geometry.crossings import Crossings
from rebar_data.geometry.curves import Curve
from rebar_data.geometry.specs import Bar

RING_SIDES = 16
MAX_SAGITTA_M = 2.5e-4  # chord error allowed when sampling an arc


@dataclass(frozen=True)
class Part:
    """One solid of the mesh: a bar, or the tie wire at a crossing."""

    part_id: int
    kind: str  # "bar" | "tie_wire"
    bar_id: int  # -1 for tie wire
    crossing_id: int  # -1 for bars
    mesh: trimesh.Trimesh


def _stations(curve: Curve, realism: Realism, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Arc lengths along the bar and the tube radius at each (ribbed when asked)."""
    if realism.ribs:
        step = realism.rib_spacing_m / 8.0
    elif curve.kind == "arc":
        step = 2.0 * curve.radius * np.arccos(max(-1.0, 1.0 - MAX_SAGITTA_M / curve.radius))
    else:
        step = curve.length
    n = max(2, int(np.ceil(curve.length / step)) + 1)
    s = np.linspace(0.0, curve.length, n)
    r = np.full(n, radius)
    if realism.ribs:
        phase = np.cos(2.0 * np.pi * s / realism.rib_spacing_m)
        r = r + realism.rib_height_m * np.clip(phase, 0.0, None) ** 4
    return s, r


def _normal_frame(curve: Curve) -> np.ndarray:
    """A unit vector perpendicular to the curve's tangent everywhere along it."""
    if curve.kind == "arc":
        return curve.axis
    d = curve.direction
    helper = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    n = np.cross(d, helper)
    return n / np.linalg.norm(n)


def tube(
    curve: Curve, radius_profile: tuple[np.ndarray, np.ndarray], sides: int = RING_SIDES
) -> trimesh.Trimesh:
    """A closed tube along ``curve`` with the given (arc length, radius) profile and flat end caps."""
    s, r = radius_profile
    centers = curve.point(s)
    tangents = curve.tangent(s)
    n1 = np.broadcast_to(_normal_frame(curve), tangents.shape)
    n2 = np.cross(tangents, n1)
    ang = 2.0 * np.pi * np.arange(sides) / sides
    ring = np.cos(ang)[None, :, None] * n1[:, None, :] + np.sin(ang)[None, :, None] * n2[:, None, :]
    # circumscribed polygon: the faces touch the true cylinder, so bars that touch overlap slightly and
    # the crossing point lies inside the solid rather than in a sliver gap between two inscribed tubes
    r = r / np.cos(np.pi / sides)
    verts = (centers[:, None, :] + r[:, None, None] * ring).reshape(-1, 3)
    m = len(s)
    i = np.arange(m - 1)[:, None]
    k = np.arange(sides)[None, :]
    a = i * sides + k
    b = i * sides + (k + 1) % sides
    c = a + sides
    d = b + sides
    side = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)], 0).reshape(-1, 3)
    start_c, end_c = m * sides, m * sides + 1
    kk = np.arange(sides)
    cap0 = np.stack([np.full(sides, start_c), (kk + 1) % sides, kk], -1)
    last = (m - 1) * sides
    cap1 = np.stack([np.full(sides, end_c), last + kk, last + (kk + 1) % sides], -1)
    verts = np.vstack([verts, centers[0], centers[-1]])
    faces = np.vstack([side, cap0, cap1])
    mesh = trimesh.Trimesh(verts, faces, process=False)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def tie_wire(crossings: Crossings, index: int, bars: list[Bar], wire_diameter: float) -> trimesh.Trimesh:
    """A torus of wire looped diagonally around the two bars of one crossing."""
    if crossings.piece_a is not None:  # bars of several pieces: the pieces the crossing lies on
        a, b = bars[crossings.piece_a[index]], bars[crossings.piece_b[index]]
    else:
        a, b = bars[crossings.bar_a[index]], bars[crossings.bar_b[index]]
    n = crossings.normal[index]
    ta = a.curve.tangent(a.curve.project(crossings.point_a[index]))
    tb = b.curve.tangent(b.curve.project(crossings.point_b[index]))
    diag = ta + tb if np.dot(ta, tb) >= 0 else ta - tb
    diag = diag - np.dot(diag, n) * n
    diag /= np.linalg.norm(diag)
    loop_axis = np.cross(n, diag)
    major = a.radius_m + b.radius_m + wire_diameter
    torus = mf.Manifold.revolve(mf.CrossSection.circle(wire_diameter / 2.0, 12).translate((major, 0.0)), 24)
    mesh = _to_trimesh(torus)
    # revolve's axis is z; map x -> diag, y -> n, z -> loop_axis
    R = np.stack([diag, n, loop_axis], axis=1)
    mesh.vertices = mesh.vertices @ R.T + crossings.point[index]
    return mesh


def _to_trimesh(m: mf.Manifold) -> trimesh.Trimesh:
    g = m.to_mesh()
    return trimesh.Trimesh(np.asarray(g.vert_properties)[:, :3], np.asarray(g.tri_verts), process=False)


def _to_manifold(mesh: trimesh.Trimesh) -> mf.Manifold:
    m = mf.Manifold(
        mf.Mesh(
            vert_properties=np.asarray(mesh.vertices, np.float32),
            tri_verts=np.asarray(mesh.faces, np.uint32),
        )
    )
    if m.status() != mf.Error.NoError:
        raise RuntimeError(f"manifold3d rejected a part: {m.status()}")
    return m


def build_parts(
    bars: list[Bar], crossings: Crossings, realism: Realism, tie_rng: np.random.Generator
) -> list[Part]:
    """One watertight mesh per bar, then a tie-wire loop at a seeded share of the crossings."""
    parts = []
    for bar in bars:
        mesh = tube(bar.curve, _stations(bar.curve, realism, bar.radius_m))
        parts.append(Part(len(parts), "bar", bar.bar_id, -1, mesh))
    draws = tie_rng.random(len(crossings))
    for ci in np.nonzero(draws < realism.tie_wire_fraction)[0]:
        mesh = tie_wire(crossings, int(ci), bars, realism.tie_wire_diameter_m)
        parts.append(Part(len(parts), "tie_wire", -1, int(ci), mesh))
    return parts


def merge(parts: list[Part]) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Boolean union of all parts: one watertight mesh and the part id of each of its triangles."""
    solids = [_to_manifold(p.mesh).as_original() for p in parts]
    id_to_part = {s.original_id(): i for i, s in enumerate(solids)}
    union = mf.Manifold.batch_boolean(solids, mf.OpType.Add)
    g = union.to_mesh()
    faces = np.asarray(g.tri_verts)
    part_of_tri = np.empty(len(faces), np.int32)
    run_index = np.asarray(g.run_index)
    for k, orig in enumerate(np.asarray(g.run_original_id)):
        part_of_tri[run_index[k] // 3 : run_index[k + 1] // 3] = id_to_part[int(orig)]
    mesh = trimesh.Trimesh(np.asarray(g.vert_properties, np.float64)[:, :3], faces, process=False)
    return mesh, part_of_tri


def joint_balls(pieces: list[Bar], *, first_part_id: int, smooth_cos: float = 1.0 - 1e-9) -> list[Part]:
    """A ball of the bar's radius where two consecutive pieces of one bar meet at an angle (a polyline's
    corner), filling the wedge their flat end caps leave open. Smooth joints (a bend's arc) need none."""
    parts = []
    for prev, cur in zip(pieces, pieces[1:], strict=False):
        if prev.bar_id != cur.bar_id:
            continue
        a, b = prev.curve, cur.curve
        if np.dot(a.tangent(a.length), b.tangent(0.0)) >= smooth_cos:
            continue
        ball = mf.Manifold.sphere(prev.radius_m / np.cos(np.pi / RING_SIDES), RING_SIDES)
        mesh = _to_trimesh(ball.translate(tuple(float(x) for x in a.end)))
        parts.append(Part(first_part_id + len(parts), "bar", prev.bar_id, -1, mesh))
    return parts
