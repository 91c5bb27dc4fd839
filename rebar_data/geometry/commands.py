"""`rebar mesh`: build a rebar mesh and write it to a folder."""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path


def run_mesh(args: argparse.Namespace) -> None:
    from rebar_data.dataset.config import load_mesh_config
    from rebar_data.geometry.build import build_rebar_mesh
    from rebar_data.geometry.export import write_mesh_outputs

    cfg = load_mesh_config(args.config)
    rm = build_rebar_mesh(cfg)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # write beside the target and rename, so an interrupted run never leaves a folder that looks finished
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.tmp-") as tmp:
        write_mesh_outputs(rm, Path(tmp) / "mesh")
        if out.exists():
            shutil.rmtree(out)
        Path(tmp, "mesh").rename(out)
    if args.rrd:
        from rebar_data.geometry.recording import write_mesh_recording

        write_mesh_recording(rm, Path(args.rrd))
    print(
        f"{len(rm.bars)} bars, {len(rm.crossings)} crossings, {len(rm.mesh.faces)} triangles", file=sys.stderr
    )
    print(out)


def register(sub: argparse._SubParsersAction) -> None:
    m = sub.add_parser("mesh", help="build a rebar mesh: GLB, PLY, bars and crossings tables")
    m.add_argument("config", help="pipeline YAML, such as pipelines/paper-tunnel.yaml")
    m.add_argument("--out", required=True, help="output folder")
    m.add_argument("--rrd", help="also write a Rerun recording of the mesh and crossings")
    m.set_defaults(func=run_mesh)
