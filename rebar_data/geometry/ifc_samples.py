"""Sample IFC models the project makes itself: a reinforced wall with stirrups and bent bars, and a lift
shaft (a cage: four walls of bars around a core) drawn as mapped items.

``pipelines/ifc/wall.ifc`` (what ``pipelines/ifc-wall.yaml`` reads) is written by::

    python -m rebar_data.geometry.ifc_samples pipelines/ifc/wall.ifc

The wall is 1.6 m long, 1.2 m high and 0.2 m thick, standing on a storey, turned -60 degrees about z and
moved to (3, 2, 0.5) m, so its faces are neither axis-aligned nor at the origin. Each face has a mat of
12 mm bars at 150 mm: horizontal bars outside (cover 30 mm), vertical bars inside them, touching. Six closed
8 mm stirrups (four legs, four 20 mm bends) hold the three vertical bars at each end of both mats, and
three 10 mm U-bars (two legs, two 30 mm bends and a straight top) cap the wall between the vertical bars.

The shaft (:func:`shaft_records`) is square about the z axis, its walls ``thickness_m`` thick, ``half_m`` from the
axis to a wall's outer face, one storey of ``storey_m`` above another. Each wall has two mats of 12 mm bars at
``spacing_m``: closed horizontal loops round the shaft (four legs, four 50 mm bends) outside, vertical bars
inside them, touching; the inner mat the same way round, its loops nearest the core. With ``mapped`` the bars
are written as a placement tool writes them: per storey and mat one element of mapped items for the loops and
one each for the vertical bars of the two pairs of opposite walls.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rebar_data.geometry.curves import Arc, Curve, Line
from rebar_data.geometry.ifc_write import BarRecord, global_id, ifc_model, write_model

WALL_TIMESTAMP = 1_767_225_600  # 2026-01-01T00:00:00Z: the same bytes every time
WALL_LENGTH_M, WALL_HEIGHT_M, WALL_THICKNESS_M, COVER_M = 1.6, 1.2, 0.2, 0.03
MAT_DIAMETER_M, STIRRUP_DIAMETER_M, U_BAR_DIAMETER_M = 0.012, 0.008, 0.010
SPACING_M = 0.15
STIRRUP_BEND_M, U_BAR_BEND_M = 0.02, 0.03
WALL_YAW_DEG = -60.0
WALL_TRANSLATION_M = (3.0, 2.0, 0.5)


def _v(*xyz: float) -> np.ndarray:
    return np.array(xyz, float)


def _quarter(center: np.ndarray, radius: float, start_dir: np.ndarray, end_dir: np.ndarray) -> Arc:
    """The quarter circle about ``center`` from ``center + radius * start_dir`` to ``+ radius * end_dir``."""
    return Arc(center, radius, np.cross(start_dir, end_dir), start_dir, np.pi / 2.0)


def _stirrup(z: float, bars_x: tuple[float, float], bar_y: float) -> list[Curve]:
    """A closed rectangular stirrup in the plane ``z`` around vertical bars at ``bars_x`` (outermost) and
    ``+-bar_y``, each corner bar touching its bend on the diagonal."""
    rb = STIRRUP_BEND_M
    inset = (rb - (MAT_DIAMETER_M + STIRRUP_DIAMETER_M) / 2.0) / np.sqrt(2.0)
    cx = (bars_x[0] + inset, bars_x[1] - inset)  # bend centres
    cy = (-bar_y + inset, bar_y - inset)
    ex, ey = _v(1, 0, 0), _v(0, 1, 0)
    c = {(i, j): _v(cx[i], cy[j], z) for i in (0, 1) for j in (0, 1)}
    pieces: list[Curve] = [
        Line(c[0, 1] + rb * ey, c[1, 1] + rb * ey),  # camera-side leg, along +x
        _quarter(c[1, 1], rb, ey, ex),
        Line(c[1, 1] + rb * ex, c[1, 0] + rb * ex),  # across the thickness, along -y
        _quarter(c[1, 0], rb, ex, -ey),
        Line(c[1, 0] - rb * ey, c[0, 0] - rb * ey),  # far leg, along -x
        _quarter(c[0, 0], rb, -ey, -ex),
        Line(c[0, 0] - rb * ex, c[0, 1] - rb * ex),  # across, along +y
        _quarter(c[0, 1], rb, -ex, ey),
    ]
    return pieces


def _u_bar(x: float, leg_y: float, z_low: float, z_top: float) -> list[Curve]:
    """A U-bar in the plane ``x``: up the leg at ``+leg_y``, over the top, down the leg at ``-leg_y``."""
    rb = U_BAR_BEND_M
    ey, ez = _v(0, 1, 0), _v(0, 0, 1)
    bend_z = z_top - rb
    c_front, c_back = _v(x, leg_y - rb, bend_z), _v(x, -leg_y + rb, bend_z)
    return [
        Line(_v(x, leg_y, z_low), _v(x, leg_y, bend_z)),
        _quarter(c_front, rb, ey, ez),
        Line(c_front + rb * ez, c_back + rb * ez),
        _quarter(c_back, rb, ez, -ey),
        Line(_v(x, -leg_y, bend_z), _v(x, -leg_y, z_low)),
    ]


@dataclass(frozen=True)
class WallSpec:
    """The sample wall's size and its mats' bars: the shipped wall.ifc by default (12 mm at 150 mm)."""

    length_m: float = WALL_LENGTH_M
    height_m: float = WALL_HEIGHT_M
    thickness_m: float = WALL_THICKNESS_M
    mat_diameter_m: float = MAT_DIAMETER_M
    spacing_m: float = SPACING_M
    rows: int = 7  # horizontal bars a mat, from 0.1 m up
    columns: int = 10  # vertical bars a mat, centred


def wall_bars(spec: WallSpec = WallSpec()) -> list[tuple[list[Curve], float, str]]:
    """The wall's bars in its own frame (x along it, y through it, z up from its base): pieces, diameter
    and IFC role."""
    half_l, t, d, step = spec.length_m / 2.0, spec.thickness_m, spec.mat_diameter_m, spec.spacing_m
    y_h = t / 2.0 - COVER_M - d / 2.0  # horizontal bars, outside
    y_v = y_h - d  # vertical bars, inside them, touching
    z_h = np.arange(spec.rows) * step + 0.1
    x_v = (np.arange(spec.columns) - (spec.columns - 1) / 2.0) * step
    bars: list[tuple[list[Curve], float, str]] = []
    for side in (1.0, -1.0):
        for z in z_h:
            line = Line(_v(-half_l + COVER_M, side * y_h, z), _v(half_l - COVER_M, side * y_h, z))
            bars.append(([line], d, "MAIN"))
        for x in x_v:
            line = Line(_v(x, side * y_v, COVER_M), _v(x, side * y_v, spec.height_m - COVER_M))
            bars.append(([line], d, "MAIN"))
    for end in (-1.0, 1.0):
        outer = x_v[-1] if end > 0 else x_v[0]
        inner = outer - end * 2 * step
        span = (min(inner, outer), max(inner, outer))
        for z in z_h[:-1][::2] + step / 2.0:
            bars.append((_stirrup(float(z), span, y_v), STIRRUP_DIAMETER_M, "LIGATURE"))
    for x in (-0.3, 0.0, 0.3):
        bars.append((_u_bar(x, y_v, 0.6, spec.height_m - 0.06), U_BAR_DIAMETER_M, "EDGE"))
    return bars


def world_from_wall() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", WALL_YAW_DEG, degrees=True).as_matrix()
    T[:3, 3] = WALL_TRANSLATION_M
    return T


def wall_records(spec: WallSpec = WallSpec()) -> list[BarRecord]:
    """The wall's bars placed in the world, as the IFC writer takes them."""
    T = world_from_wall()
    R, t = T[:3, :3], T[:3, 3]
    return [
        BarRecord(k, [c.transformed(R, t) for c in curves], d, -1, -1, global_id(f"ifc-wall/{k}"), role)
        for k, (curves, d, role) in enumerate(wall_bars(spec))
    ]


def write_wall(path: str | Path, *, schema: str = "IFC4", spec: WallSpec = WallSpec()) -> Path:
    """Write the sample wall to ``path`` (the same bytes for the same IfcOpenShell version)."""
    path = Path(path)
    model = ifc_model(
        wall_records(spec),
        schema=schema,
        project_name="ifc-wall",
        file_name=path.name,
        timestamp=WALL_TIMESTAMP,
    )
    return write_model(model, path)


def _loop(half: float, z: float, bend: float) -> list[Curve]:
    """A closed square loop about the z axis at height ``z``, ``half`` from the axis to its legs' axes."""
    pieces: list[Curve] = []
    c = half - bend
    for k in range(4):
        out, along = Rotation.from_euler("z", 90.0 * k, degrees=True).as_matrix()[:, :2].T
        up = _v(0, 0, z)
        pieces.append(Line(half * out - c * along + up, half * out + c * along + up))
        pieces.append(_quarter(c * out + c * along + up, bend, out, along))
    return pieces


def shaft_records(
    *,
    storeys: int = 1,
    half_m: float = 1.3,
    thickness_m: float = 0.25,
    storey_m: float = 3.0,
    spacing_m: float = 0.15,
    mapped: bool = True,
) -> list[BarRecord]:
    """The lift shaft's bars (module doc), in the world: the shaft's axis is z, its base at z = 0."""
    d, cover, bend = MAT_DIAMETER_M, COVER_M, 0.05
    loops_outer = half_m - cover - d / 2.0
    loops_inner = half_m - thickness_m + cover + d / 2.0
    mats = (("outer", loops_outer, loops_outer - d), ("inner", loops_inner, loops_inner + d))
    levels = np.arange(spacing_m / 2.0, storey_m - cover, spacing_m)
    bars: list[tuple[list[Curve], str]] = []
    for storey in range(storeys):
        z0 = storey * storey_m
        for name, loop_half, vertical_half in mats:
            for z in levels:
                bars.append((_loop(loop_half, z0 + z, bend), f"{storey}/{name}/loops"))
            n = int(np.floor(2.0 * (vertical_half - bend - 0.05) / spacing_m)) + 1
            along = (np.arange(n) - (n - 1) / 2.0) * spacing_m
            for k in range(4):
                out, side = Rotation.from_euler("z", 90.0 * k, degrees=True).as_matrix()[:, :2].T
                for u in along:
                    foot = vertical_half * out + u * side + _v(0, 0, z0 + cover)
                    bars.append(
                        ([Line(foot, foot + _v(0, 0, storey_m - 2 * cover))], f"{storey}/{name}/v{k % 2}")
                    )
    return [
        BarRecord(k, curves, d, -1, -1, global_id(f"ifc-shaft/{k}"), "MAIN", group if mapped else None)
        for k, (curves, group) in enumerate(bars)
    ]


def write_shaft(path: str | Path, **shape) -> Path:
    """Write the lift shaft (:func:`shaft_records`'s keywords) to ``path``."""
    path = Path(path)
    model = ifc_model(
        shaft_records(**shape), project_name="ifc-shaft", file_name=path.name, timestamp=WALL_TIMESTAMP
    )
    return write_model(model, path)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="Write the sample IFC wall (stirrups and bent bars).")
    p.add_argument("out", help="the .ifc file to write, such as pipelines/ifc/wall.ifc")
    p.add_argument("--schema", choices=("IFC4", "IFC2X3"), default="IFC4")
    p.add_argument("--size-m", type=float, nargs=3, metavar=("LENGTH", "HEIGHT", "THICKNESS"))
    p.add_argument("--bar-mm", type=float, help=f"the mats' bar diameter (default {MAT_DIAMETER_M * 1000:g})")
    p.add_argument("--spacing-mm", type=float, help=f"the mats' spacing (default {SPACING_M * 1000:g})")
    p.add_argument("--rows", type=int, help="horizontal bars a mat (default 7)")
    p.add_argument("--columns", type=int, help="vertical bars a mat (default 10)")
    args = p.parse_args(argv)
    spec = WallSpec()
    if args.size_m:
        spec = replace(spec, length_m=args.size_m[0], height_m=args.size_m[1], thickness_m=args.size_m[2])
    if args.bar_mm:
        spec = replace(spec, mat_diameter_m=args.bar_mm / 1000.0)
    if args.spacing_mm:
        spec = replace(spec, spacing_m=args.spacing_mm / 1000.0)
    if args.rows:
        spec = replace(spec, rows=args.rows)
    if args.columns:
        spec = replace(spec, columns=args.columns)
    print(write_wall(args.out, schema=args.schema, spec=spec))


if __name__ == "__main__":
    main()
