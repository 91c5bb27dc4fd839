"""The mesh sections of a pipeline file: the bar grid (planar, tunnel segment, or an IFC model's bars), its
realism options and its pose, as ``rebar mesh`` reads them (:class:`MeshConfig`). The rest of a pipeline file is
:mod:`rebar_data.pipeline` and :mod:`rebar_data.scene.config`; the machinery every schema uses (``Strict``, the
YAML reader, the error messages) is :mod:`rebar_data.config`."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from rebar_data.config import ConfigError, Fraction, NonNegative, Positive, Strict, Vec3, excerpt


class Layer(Strict):
    """One reinforcement mat: two crossing bar directions at a face of the element.

    ``face`` is the side of the element the mat sits against: ``top`` (for a tunnel segment, the
    extrados) or ``bottom`` (the intrados). Direction-0 bars lie nearer the face, direction-1 bars
    beneath them, touching. ``offset_m`` shifts the bar pattern in the plane of the mat.
    """

    face: Literal["top", "bottom"] = "top"
    cover_m: NonNegative | None = None
    offset_m: tuple[float, float] = (0.0, 0.0)


class MeshBase(Strict):
    bar_diameter_m: Positive = 0.012
    cover_m: NonNegative = 0.05
    end_cover_m: NonNegative = 0.05
    crossing_tolerance_m: NonNegative = 0.005
    layers: list[Layer] = Field(default_factory=lambda: [Layer()], min_length=1)


class PlanarMesh(MeshBase):
    """Planar slab of ``width_m`` (x) by ``height_m`` (y); direction 0 bars run along x."""

    kind: Literal["planar"]
    width_m: Positive
    height_m: Positive
    thickness_m: Positive = 0.25
    spacing_x_m: Positive = 0.1
    spacing_y_m: Positive = 0.1

    @model_validator(mode="after")
    def _fits(self) -> PlanarMesh:
        _check_fits("spacing_x_m", self.spacing_x_m, "width_m", self.width_m, self.end_cover_m)
        _check_fits("spacing_y_m", self.spacing_y_m, "height_m", self.height_m, self.end_cover_m)
        _check_thickness(self)
        return self


class TunnelSegmentMesh(MeshBase):
    """Curved tunnel-segment mat: hoop bars (arcs, direction 0) and longitudinal bars (lines, direction 1).

    The segment is a cylindrical shell of ``thickness_m`` whose inner and outer arc lengths are
    ``intrados_arc_m`` and ``extrados_arc_m`` and whose length along the tunnel axis is ``width_m``; the
    three fix the segment's angle and radii. ``spacing_axial_m`` separates hoop bars along the axis,
    ``spacing_arc_m`` separates longitudinal bars along the arc.
    """

    kind: Literal["tunnel_segment"]
    intrados_arc_m: Positive
    extrados_arc_m: Positive
    width_m: Positive
    thickness_m: Positive = 0.30
    spacing_axial_m: Positive = 0.1
    spacing_arc_m: Positive = 0.1

    @model_validator(mode="after")
    def _fits(self) -> TunnelSegmentMesh:
        if self.extrados_arc_m <= self.intrados_arc_m:
            raise ValueError(
                f"extrados_arc_m = {self.extrados_arc_m} must be longer than intrados_arc_m = "
                f"{self.intrados_arc_m} (the outer arc of a segment is the longer one)"
            )
        if self.angle_rad >= np.pi:
            raise ValueError(
                f"the segment spans {np.degrees(self.angle_rad):.0f} degrees; accepted: under 180 "
                "(increase thickness_m or bring the two arc lengths closer)"
            )
        _check_fits("spacing_axial_m", self.spacing_axial_m, "width_m", self.width_m, self.end_cover_m)
        _check_fits(
            "spacing_arc_m", self.spacing_arc_m, "intrados_arc_m", self.intrados_arc_m, self.end_cover_m
        )
        _check_thickness(self)
        return self

    @property
    def angle_rad(self) -> float:
        return (self.extrados_arc_m - self.intrados_arc_m) / self.thickness_m

    @property
    def intrados_radius_m(self) -> float:
        return self.intrados_arc_m / self.angle_rad

    @property
    def extrados_radius_m(self) -> float:
        return self.extrados_arc_m / self.angle_rad


_GLOBAL_ID = re.compile(r"^[0-9A-Za-z_$]{22}$")
_IFC_CLASS = re.compile(r"^Ifc[A-Za-z0-9]+$")


class IfcMesh(Strict):
    """Bars read from an IFC building model: each IfcSweptDiskSolid of a selected element is one bar.

    ``ifc_path`` is read relative to the pipeline file. The filters narrow the elements: ``ifc_classes``
    (the element classes taken, subclasses included), ``storeys`` (names or GlobalIds of the storeys that
    contain them), ``global_ids`` (the elements themselves) and ``bbox_m`` (``[[x, y, z], [x, y, z]]``, the
    model's world frame in metres: bars whose centerline passes through the box, kept whole). A bar without
    a centerline the reader understands stops the build, unless ``skip_unreadable`` lets it go on (the bars
    left out are listed in mesh.json). Two bars cross where their centerlines come within the two radii
    plus ``crossing_tolerance_m`` at an angle of at least ``min_crossing_angle_deg`` (lapped bars run side
    by side and do not cross). Cameras and lights face a plane or cylinder fitted to the bars' centerlines
    (for a cage, one of its faces), from its ``camera_side``; the bars are sorted into mats by their height above it (a crossing's ``layer``
    is its mat, 0 the top mat), and ``crossings: top_mat`` keeps only the top mat's crossings (see
    :mod:`rebar_data.geometry.surface_fit` for the rules).
    """

    kind: Literal["ifc"]
    ifc_path: Annotated[str, Field(min_length=1)]
    ifc_classes: list[str] = Field(
        default_factory=lambda: ["IfcReinforcingBar", "IfcReinforcingMesh"], min_length=1
    )
    storeys: Annotated[list[str], Field(min_length=1)] | None = None
    global_ids: Annotated[list[str], Field(min_length=1)] | None = None
    bbox_m: tuple[Vec3, Vec3] | None = None
    skip_unreadable: bool = False
    crossing_tolerance_m: NonNegative = 0.005
    min_crossing_angle_deg: Annotated[float, Field(gt=0, le=90)] = 10.0
    surface: Literal["auto", "plane", "cylinder"] = Field(
        "auto",
        description="the surface fitted to the bars that cameras and lights face: auto takes a cylinder when "
        "it fits better and more bars lie along it",
    )
    camera_side: Vec3 | None = Field(
        None,
        description="a direction (the model's frame, before pose) on the camera's side of the surface; default "
        "up (+z; +x, then +y for a vertical surface), a cylinder's outside; for a cage, the face it points out of",
    )
    mat_gap_m: Positive | None = Field(
        None,
        description="bars whose heights above the surface differ by more than this lie in different mats; "
        "default twice the largest bar diameter",
    )
    top_mat: Annotated[int, Field(ge=0)] | None = Field(
        None,
        description="the mat the robot ties, counted from the camera side (0, the default, is the nearest)",
    )
    crossings: Literal["all", "top_mat"] = Field(
        "all",
        description="the crossings the mesh keeps (labels, tie wire, servo targets): every one found, or those of "
        "two top-mat bars",
    )

    @model_validator(mode="after")
    def _names(self) -> IfcMesh:
        for i, name in enumerate(self.ifc_classes):
            if not _IFC_CLASS.match(name):
                raise ValueError(
                    f"ifc_classes[{i}] = {excerpt(name)} is not an IFC class name; accepted: names such as "
                    "IfcReinforcingBar, IfcReinforcingMesh, IfcTendon"
                )
        for i, gid in enumerate(self.global_ids or []):
            if not _GLOBAL_ID.match(gid):
                raise ValueError(
                    f"global_ids[{i}] = {excerpt(gid)} is not a GlobalId; accepted: 22 characters of 0-9, A-Z, a-z, "
                    "_ and $ (IFC's compressed GUID)"
                )
        if self.camera_side is not None and not (
            all(np.isfinite(self.camera_side)) and float(np.linalg.norm(self.camera_side)) > 0.0
        ):
            raise ValueError(
                f"camera_side = {list(self.camera_side)} is not accepted: it must be a finite, non-zero "
                "direction, such as [0, 0, 1] (from above)"
            )
        if self.bbox_m is not None and not all(a < b for a, b in zip(*self.bbox_m, strict=True)):
            raise ValueError(
                f"bbox_m = {[list(c) for c in self.bbox_m]} is not accepted: its first corner must be below "
                "its second on every axis ([[x_min, y_min, z_min], [x_max, y_max, z_max]])"
            )
        return self

    def path(self, config_dir: Path | None) -> Path:
        """The IFC file: ``ifc_path`` as given when absolute, else relative to the pipeline's folder."""
        p = Path(self.ifc_path).expanduser()
        if p.is_absolute():
            return p
        if config_dir is None:
            raise ConfigError(
                f"mesh.ifc_path = {self.ifc_path!r} is relative to the pipeline file, which this command "
                "does not know; accepted: an absolute path here"
            )
        return Path(config_dir) / p


def _check_fits(spacing_name: str, spacing: float, extent_name: str, extent: float, end_cover: float) -> None:
    usable = extent - 2 * end_cover
    if spacing > usable:
        raise ValueError(
            f"{spacing_name} = {spacing} is larger than the mesh: {extent_name} = {extent} less twice "
            f"end_cover_m leaves {usable:.4g} m; accepted: a spacing of at most {usable:.4g} m"
        )


def _check_thickness(mesh: MeshBase) -> None:
    for i, layer in enumerate(mesh.layers):
        cover = mesh.cover_m if layer.cover_m is None else layer.cover_m
        need = cover + 2 * mesh.bar_diameter_m
        room = mesh.thickness_m / 2 if len(mesh.layers) > 1 else mesh.thickness_m
        if need > room:
            raise ValueError(
                f"layers[{i}]: cover {cover} m plus two bars of {mesh.bar_diameter_m} m does not fit in "
                f"thickness_m = {mesh.thickness_m}; accepted: a thicker element or less cover"
            )


class Pose(Strict):
    """Rigid pose of the mesh in the world: XYZ Euler angles (degrees, extrinsic) then translation."""

    translation_m: Vec3 = (0.0, 0.0, 0.0)
    rotation_deg: Vec3 = (0.0, 0.0, 0.0)


class Realism(Strict):
    """Seeded departures from the ideal grid. All default to off."""

    ribs: bool = False
    rib_spacing_m: Positive = 0.008
    rib_height_m: NonNegative = 0.0006
    tie_wire_fraction: Fraction = 0.0
    tie_wire_diameter_m: Positive = 0.0016
    jitter_m: NonNegative = 0.0
    jitter_normal_m: NonNegative = 0.0
    bow_m: NonNegative = 0.0
    missing_fraction: Annotated[float, Field(ge=0, lt=1)] = 0.0
    diameters_m: list[Positive] | None = None
    pose_jitter_translation_m: NonNegative = 0.0
    pose_jitter_rotation_deg: NonNegative = 0.0


class MeshConfig(Strict):
    """What ``rebar mesh`` needs: the grid, its realism options, its pose and the seed."""

    seed: Annotated[int, Field(ge=0)] = 0
    mesh: Annotated[PlanarMesh | TunnelSegmentMesh | IfcMesh, Field(discriminator="kind")]
    realism: Realism = Realism()
    pose: Pose = Pose()
