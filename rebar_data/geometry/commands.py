"""`rebar mesh`: build a rebar mesh and write it to a folder."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

COMMAND = "rebar mesh"
MESH_FILES = ("mesh.json", "mesh.glb", "bars.parquet", "crossings.parquet")
RECORDING_ID = b"rebar_mesh"  # the recording's application id, near the start of the file


def is_mesh_folder(folder: Path) -> bool:
    """``folder`` has the layout of an earlier `rebar mesh` output (written before outputs carried a mark)."""
    return all((folder / name).is_file() for name in MESH_FILES)


def is_mesh_recording(path: Path) -> bool:
    """``path`` is a Rerun recording that `rebar mesh --rrd` wrote."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return head.startswith(b"RRF") and RECORDING_ID in head


def require_ifcopenshell(what: str) -> None:
    """IfcOpenShell (the ``ifc`` extra) is installed, or one line saying how to install it."""
    from rebar_data.config import ConfigError

    try:
        import ifcopenshell  # noqa: F401
    except ImportError:
        raise ConfigError(
            f"{what} needs IfcOpenShell, which is not installed; accepted: install it with "
            '`pip install -e ".[ifc]"` (make setup does)'
        ) from None


def run_mesh(args: argparse.Namespace) -> None:
    from rebar_data.config import ConfigError
    from rebar_data.geometry.build import build_rebar_mesh
    from rebar_data.geometry.export import write_mesh_outputs
    from rebar_data.outputs import (
        OutputLock,
        mark_output,
        output_file,
        output_folder,
        remove_stale,
        replace_folder,
    )
    from rebar_data.pipeline import load_mesh_config

    def check_out() -> Path:
        return output_folder(args.out, arg="--out", command=COMMAND, owned=is_mesh_folder, swapped=True)

    out = check_out()
    rrd = None
    if args.rrd:
        rrd = output_file(
            args.rrd,
            arg="--rrd",
            what="a .rrd file, new or an earlier `rebar mesh` recording",
            owned=is_mesh_recording,
        )
        if rrd.suffix != ".rrd":
            raise ConfigError(f"--rrd {rrd}: is not a .rrd file name; accepted: a file name ending in .rrd")
    ifc = None
    if args.ifc:
        require_ifcopenshell("--ifc")
        from rebar_data.geometry.ifc_write import is_mesh_ifc

        ifc = output_file(
            args.ifc,
            arg="--ifc",
            what="a .ifc file, new or an earlier `rebar mesh` IFC file",
            owned=is_mesh_ifc,
        )
        if ifc.suffix.lower() != ".ifc":
            raise ConfigError(f"--ifc {ifc}: is not a .ifc file name; accepted: a file name ending in .ifc")
        if ifc.absolute().is_relative_to(out.absolute()):
            raise ConfigError(
                f"--ifc {ifc}: lies in --out {out}, which is replaced whole; accepted: a path outside --out"
            )
    cfg = load_mesh_config(args.config)
    config_dir = Path(args.config).parent
    if cfg.mesh.kind == "ifc":
        require_ifcopenshell("mesh.kind: ifc")
        source = cfg.mesh.path(config_dir)
        if source.resolve().is_relative_to(out.resolve()):
            raise ConfigError(
                f"--out {out}: holds the model mesh.ifc_path reads ({source}), and it would be replaced; "
                "accepted: a folder that does not hold the input"
            )
        if ifc is not None and ifc.resolve() == source.resolve():
            raise ConfigError(
                f"--ifc {ifc}: is the model mesh.ifc_path reads, which it would overwrite; accepted: another file"
            )
    rm = build_rebar_mesh(cfg, config_dir=config_dir)
    with OutputLock(out, command=COMMAND):
        check_out()  # again under the lock: another writer may have finished there meanwhile
        remove_stale(out.parent, f".{out.name}.tmp-*")  # a killed run's (the lock proves it dead)
        # write beside the target and swap, so an interrupted run never leaves a folder that looks finished
        with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.tmp-") as tmp:
            staging = Path(tmp) / "mesh"
            write_mesh_outputs(rm, staging)
            mark_output(staging, COMMAND)
            replace_folder(staging, out)
    if rrd is not None:
        from rebar_data.geometry.recording import write_mesh_recording

        with OutputLock(rrd, command=COMMAND, arg="--rrd"):
            write_mesh_recording(rm, rrd)
    if ifc is not None:
        from rebar_data.geometry.ifc_write import write_ifc

        with OutputLock(ifc, command=COMMAND, arg="--ifc"):
            write_ifc(rm, ifc, project_name=Path(args.config).stem)
    n_bars = len({b.bar_id for b in rm.bars})
    src = rm.layout.ifc
    skipped = len({s["global_id"] for s in src.skipped}) if src is not None else 0
    dropped = len(src.dropped) if src is not None else 0
    print(
        f"{n_bars} bars, {len(rm.crossings)} crossings, {len(rm.mesh.faces)} triangles"
        + (f"; {skipped} IFC element{'s' * (skipped != 1)} not read whole" if skipped else "")
        + (f"; {dropped} stub{'s' * (dropped != 1)} shorter than its diameter dropped" if dropped else "")
        + ("; listed in mesh.json" if skipped or dropped else ""),
        file=sys.stderr,
    )
    print(out)


def register(sub: argparse._SubParsersAction) -> None:
    m = sub.add_parser("mesh", help="build a rebar mesh: GLB, PLY, bars and crossings tables")
    m.add_argument("config", help="pipeline YAML, such as pipelines/paper-tunnel.yaml")
    m.add_argument(
        "--out",
        required=True,
        help="output folder: new, empty, or an earlier `rebar mesh` output, which is replaced whole",
    )
    m.add_argument(
        "--rrd",
        help="also write a Rerun recording of the mesh and crossings (a new .rrd file, or an earlier one)",
    )
    m.add_argument(
        "--ifc",
        help="also write the bars as an IFC4 file (IfcReinforcingBar, swept disk solids; no tie wire), a new "
        ".ifc file or an earlier one; needs the ifc extra",
    )
    m.set_defaults(func=run_mesh)
