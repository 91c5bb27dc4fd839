"""One call from a mesh config to the finished rebar mesh: bars, crossings, solids and the merged mesh."""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np
import trimesh

from rebar_data.geometry.config import MeshConfig
from rebar_data.geometry.crossings import Crossings, find_crossings
from rebar_data.geometry.solids import Part, build_parts, merge
from rebar_data.geometry.specs import Bar, MeshLayout, build_layout


@dataclass(frozen=True)
class RebarMesh:
    """Everything later stages need about the mesh.

    ``triangle_part_id`` maps each triangle of ``mesh`` to its part; ``triangle_bar_id`` to the bar it
    belongs to (-1 for tie wire). Renderers use these for exact instance ids.
    """

    config: MeshConfig
    layout: MeshLayout
    crossings: Crossings
    parts: list[Part]
    mesh: trimesh.Trimesh
    triangle_part_id: np.ndarray

    @property
    def bars(self) -> list[Bar]:
        return self.layout.bars

    @cached_property
    def part_bar_id(self) -> np.ndarray:
        return np.array([p.bar_id for p in self.parts], np.int32)

    @cached_property
    def part_crossing_id(self) -> np.ndarray:
        return np.array([p.crossing_id for p in self.parts], np.int32)

    @cached_property
    def triangle_bar_id(self) -> np.ndarray:
        return self.part_bar_id[self.triangle_part_id]


def build_rebar_mesh(cfg: MeshConfig, *, config_dir: Path | None = None) -> RebarMesh:
    """The mesh ``cfg`` describes. ``config_dir``: the pipeline file's folder, which a relative
    ``mesh.ifc_path`` is read from."""
    if cfg.mesh.kind == "ifc":
        return _build_ifc_mesh(cfg, config_dir)
    layout = build_layout(cfg)
    crossings = find_crossings(layout, cfg.mesh.crossing_tolerance_m)
    parts = build_parts(layout.bars, crossings, cfg.realism, layout.rngs["tie_wire"])
    mesh, part_of_tri = merge(parts)
    return RebarMesh(cfg, layout, crossings, parts, mesh, part_of_tri)


def _build_ifc_mesh(cfg: MeshConfig, config_dir: Path | None) -> RebarMesh:
    """Bars read from an IFC model: the same tube sweep for every piece (a ball at each sharp joint of a
    bar's pieces, so a polyline stirrup's corners are solid) and the same exact solver for the crossings.
    The crossings' normals point to the camera side of their face (a cage's own wall); with ``mesh.crossings: top_mat`` only
    the crossings of two pieces in the top mat are kept."""
    from rebar_data.geometry.crossings import find_piece_crossings
    from rebar_data.geometry.ifc_read import ifc_layout
    from rebar_data.geometry.solids import joint_balls

    layout = ifc_layout(cfg, config_dir)
    crossings = find_piece_crossings(layout, cfg.mesh.crossing_tolerance_m, cfg.mesh.min_crossing_angle_deg)
    fit = layout.surface
    if cfg.mesh.crossings == "top_mat":
        crossings = crossings.take(np.flatnonzero(crossings.layer == fit.top_mat))
    outside = layout.faces.normal(crossings.point, crossings.piece_a)  # each crossing's own face
    facing = np.sum(crossings.normal * outside, axis=1) if len(crossings) else np.zeros(0)
    crossings = replace(crossings, normal=np.where(facing[:, None] < 0, -crossings.normal, crossings.normal))
    parts = build_parts(layout.bars, crossings, cfg.realism, layout.rngs["tie_wire"])
    parts += joint_balls(layout.bars, first_part_id=len(parts))
    mesh, part_of_tri = merge(parts)
    return RebarMesh(cfg, layout, crossings, parts, mesh, part_of_tri)
