"""One call from a mesh config to the finished rebar mesh: bars, crossings, solids and the merged mesh."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import trimesh

from rebar_data.config import MeshConfig
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


def build_rebar_mesh(cfg: MeshConfig) -> RebarMesh:
    layout = build_layout(cfg)
    crossings = find_crossings(layout, cfg.mesh.crossing_tolerance_m)
    parts = build_parts(layout.bars, crossings, cfg.realism, layout.rngs["tie_wire"])
    mesh, part_of_tri = merge(parts)
    return RebarMesh(cfg, layout, crossings, parts, mesh, part_of_tri)
