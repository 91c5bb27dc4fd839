"""Mesh specs to bar centerlines: planar slabs and curved tunnel segments, one or more layers, seeded realism.

Local frames (before the mesh pose):
- planar: origin at the slab's centre, z up (normal of the faces), slab between z = -t/2 and +t/2;
  direction-0 bars run along x, direction-1 bars along y.
- tunnel segment: tunnel axis along x through (0, 0, -R_mid), with R_mid the mid-thickness radius, so
  the crown of the mid-surface is the origin and +z is the outward normal there; direction-0 bars are
  hoops (arcs about the axis), direction-1 bars are longitudinal lines.

In every layer the direction-0 bars lie against the face (their outer surface at the cover) and the
direction-1 bars lie beneath them, touching the thickest direction-0 bar.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from rebar_data.geometry.config import Layer, MeshConfig, PlanarMesh, TunnelSegmentMesh
from rebar_data.geometry.curves import Arc, Curve, Line

if TYPE_CHECKING:
    from rebar_data.geometry.surface_fit import Faces, SurfaceFit

STREAMS = ("diameter", "missing", "jitter", "bow", "tie_wire", "pose")


@dataclass(frozen=True)
class Bar:
    bar_id: int
    curve: Curve
    diameter_m: float
    direction: int
    layer: int

    @property
    def radius_m(self) -> float:
        return self.diameter_m / 2.0


@dataclass(frozen=True)
class IfcSource:
    """Where the pieces of a mesh read from IFC come from: one entry per piece of ``MeshLayout.bars``
    (a bar of several pieces repeats its ``bar_id``), and what the reader left out."""

    path: str
    sha256: str  # of the file read
    schema: str
    elements: int  # elements the filters selected
    global_id: list[str]
    ifc_class: list[str]
    piece: list[int]  # index of the piece along its bar
    role: list[str | None]
    skipped: list[dict] = field(default_factory=list)  # entity, global_id, ifc_class, reason: not read
    dropped: list[dict] = field(default_factory=list)  # the same for the stubs left out


@dataclass(frozen=True)
class MeshLayout:
    """The bars of a mesh in the world, with the pose that put them there and the element's normals."""

    bars: list[Bar]
    world_from_mesh: np.ndarray  # 4x4
    kind: str
    axis_point: np.ndarray | None = None  # tunnel only, in the mesh frame
    rngs: dict[str, np.random.Generator] = field(default_factory=dict, repr=False)
    ifc: IfcSource | None = None  # a mesh read from IFC (kind "ifc")
    surface: SurfaceFit | None = None  # kind "ifc": the surface fitted to the bars, and their mats
    faces: Faces | None = None  # kind "ifc": every face (a cage has several); ``surface`` is the chosen one

    def outward_normal(self, points_world: np.ndarray) -> np.ndarray:
        """Outward unit normal of the element's surface at (or beside) world points, shape (N, 3); for a
        mesh read from IFC, the fitted surface's normal on its camera side."""
        if self.surface is not None:
            return self.surface.normal(points_world)
        R, t = self.world_from_mesh[:3, :3], self.world_from_mesh[:3, 3]
        local = (np.atleast_2d(points_world) - t) @ R
        if self.kind == "planar":
            n = np.tile([0.0, 0.0, 1.0], (len(local), 1))
        else:
            radial = local - self.axis_point
            radial[:, 0] = 0.0
            n = radial / np.linalg.norm(radial, axis=1, keepdims=True)
        return n @ R.T


def rng_streams(seed: int) -> dict[str, np.random.Generator]:
    """One generator per kind of randomness, so turning one option on leaves the others' draws unchanged."""
    children = np.random.SeedSequence(seed).spawn(len(STREAMS))
    return {name: np.random.default_rng(s) for name, s in zip(STREAMS, children, strict=True)}


def positions(extent: float, spacing: float, end_cover: float, offset: float) -> np.ndarray:
    """Bar positions centred on the extent, ``spacing`` apart, kept ``end_cover`` inside each edge."""
    usable = extent - 2.0 * end_cover
    n = int(np.floor(usable / spacing + 1e-9)) + 1
    p = (np.arange(n) - (n - 1) / 2.0) * spacing + offset
    return p[np.abs(p) <= usable / 2.0 + 1e-12]


def build_layout(cfg: MeshConfig) -> MeshLayout:
    """All bars of the configured mesh, posed in the world, with the seeded realism applied."""
    rngs = rng_streams(cfg.seed)
    mesh = cfg.mesh
    world_from_mesh = _pose(cfg, rngs["pose"])
    raw: list[tuple[Curve, float, int, int]] = []
    for li, layer in enumerate(mesh.layers):
        cover = mesh.cover_m if layer.cover_m is None else layer.cover_m
        builder = _planar_layer if isinstance(mesh, PlanarMesh) else _tunnel_layer
        for curve, diameter, direction in builder(mesh, layer, cover, cfg, rngs):
            raw.append((curve, diameter, direction, li))
    R, t = world_from_mesh[:3, :3], world_from_mesh[:3, 3]
    bars = [Bar(i, c.transformed(R, t), d, direction, li) for i, (c, d, direction, li) in enumerate(raw)]
    axis_point = None
    if isinstance(mesh, TunnelSegmentMesh):
        axis_point = np.array([0.0, 0.0, -_mid_radius(mesh)])
    return MeshLayout(bars, world_from_mesh, mesh.kind, axis_point, rngs)


def _pose(cfg: MeshConfig, rng: np.random.Generator) -> np.ndarray:
    real = cfg.realism
    rot = np.asarray(cfg.pose.rotation_deg, float) + rng.normal(0, 1, 3) * real.pose_jitter_rotation_deg
    trans = np.asarray(cfg.pose.translation_m, float) + rng.normal(0, 1, 3) * real.pose_jitter_translation_m
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rot, degrees=True).as_matrix()
    T[:3, 3] = trans
    return T


class _BarDraws:
    """Per-bar random draws, taken for every planned bar (present or not) in a fixed order."""

    def __init__(self, cfg: MeshConfig, rngs: dict[str, np.random.Generator]):
        self.cfg, self.rngs = cfg, rngs

    def __call__(self) -> tuple[bool, float, float, float, float]:
        real, r = self.cfg.realism, self.rngs
        choices = real.diameters_m or [self.cfg.mesh.bar_diameter_m]
        diameter = float(choices[r["diameter"].integers(len(choices))])
        present = bool(r["missing"].random() >= real.missing_fraction)
        jit = np.clip(r["jitter"].normal(0, 1, 2), -3, 3)
        sag = float(r["bow"].random() * real.bow_m)
        return present, diameter, float(jit[0] * real.jitter_m), float(jit[1] * real.jitter_normal_m), sag

    @property
    def max_diameter(self) -> float:
        return max(self.cfg.realism.diameters_m or [self.cfg.mesh.bar_diameter_m])


def _maybe_bowed(line: Line, sag: float, outward: np.ndarray) -> Curve:
    """A straight bar sagging by ``sag`` at midspan (towards the inside of the element) becomes an arc."""
    if sag < 1e-6:
        return line
    return Arc.through(line.start, line.end, -outward, sag)


def _planar_layer(mesh: PlanarMesh, layer: Layer, cover: float, cfg: MeshConfig, rngs):
    draw = _BarDraws(cfg, rngs)
    sign = 1.0 if layer.face == "top" else -1.0
    face = sign * mesh.thickness_m / 2.0
    e = mesh.end_cover_m
    hx, hy = mesh.width_m / 2.0 - e, mesh.height_m / 2.0 - e
    up = np.array([0.0, 0.0, sign])
    # direction 0: along x, placed along y
    for y in positions(mesh.height_m, mesh.spacing_y_m, e, layer.offset_m[1]):
        present, d, dj, dn, sag = draw()
        if present:
            z = face - sign * (cover + d / 2.0) + dn
            line = Line(np.array([-hx, y + dj, z]), np.array([hx, y + dj, z]))
            yield _maybe_bowed(line, sag, up), d, 0
    # direction 1: along y, placed along x, beneath direction 0
    for x in positions(mesh.width_m, mesh.spacing_x_m, e, layer.offset_m[0]):
        present, d, dj, dn, sag = draw()
        if present:
            z = face - sign * (cover + draw.max_diameter + d / 2.0) + dn
            line = Line(np.array([x + dj, -hy, z]), np.array([x + dj, hy, z]))
            yield _maybe_bowed(line, sag, up), d, 1


def _mid_radius(mesh: TunnelSegmentMesh) -> float:
    return (mesh.intrados_radius_m + mesh.extrados_radius_m) / 2.0


def _tunnel_layer(mesh: TunnelSegmentMesh, layer: Layer, cover: float, cfg: MeshConfig, rngs):
    draw = _BarDraws(cfg, rngs)
    r_mid = _mid_radius(mesh)
    center = np.array([0.0, 0.0, -r_mid])
    if layer.face == "top":
        r_face, sign = mesh.extrados_radius_m, 1.0
    else:
        r_face, sign = mesh.intrados_radius_m, -1.0
    half_angle = mesh.angle_rad / 2.0
    e = mesh.end_cover_m
    hx = mesh.width_m / 2.0 - e
    axis = np.array([-1.0, 0.0, 0.0])  # hoops turn from -psi to +psi (psi measured from +z towards +y)
    # direction 0: hoops, placed along the axis
    for x in positions(mesh.width_m, mesh.spacing_axial_m, e, layer.offset_m[0]):
        present, d, dj, dn, _ = draw()
        if present:
            r = r_face - sign * (cover + d / 2.0) + dn
            psi = half_angle - e / r
            e1 = np.array([0.0, np.sin(-psi), np.cos(-psi)])
            yield Arc(center + [x + dj, 0.0, 0.0], float(r), axis, e1, float(2 * psi)), d, 0
    # direction 1: longitudinal lines, placed along the arc, beneath the hoops
    r_lines = r_face - sign * (cover + draw.max_diameter + draw.max_diameter / 2.0)
    arc_len = mesh.angle_rad * r_lines
    for s in positions(arc_len, mesh.spacing_arc_m, e, layer.offset_m[1]):
        present, d, dj, dn, sag = draw()
        if present:
            r = r_face - sign * (cover + draw.max_diameter + d / 2.0) + dn
            psi = (s + dj) / r_lines
            radial = np.array([0.0, np.sin(psi), np.cos(psi)])
            p = center + r * radial
            line = Line(p + [-hx, 0.0, 0.0], p + [hx, 0.0, 0.0])
            yield _maybe_bowed(line, sag, radial), d, 1
