"""`rebar dataset build|validate|audit`."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from rebar_data.config import ConfigError
from rebar_data.dataset import layout


def dataset_folder(p: str) -> Path:
    """The folder ``p`` as a Path; a ConfigError naming it when it is not a folder (every dataset command)."""
    path = Path(p)
    if not path.is_dir():
        raise ConfigError(f"{p}: no such folder; accepted: a dataset folder such as data/smoke/v0.1.0")
    if not any((path / part).exists() for part in (layout.INFO, layout.MANIFEST, layout.DATA_YAML, "tables")):
        # none of a dataset's own files: a user's folder, not a damaged dataset (which validate reports)
        raise ConfigError(
            f"{p}: not a dataset folder (no {layout.INFO}, {layout.MANIFEST}, {layout.DATA_YAML} or tables/); "
            "accepted: a dataset folder such as data/smoke/v0.1.0"
        )
    return path


def run_build(args: argparse.Namespace) -> int:
    from rebar_data.dataset.build import build_dataset
    from rebar_data.ray_cluster import check_backend

    check_backend(args.backend, args.address)
    if args.backend == "ray":
        from rebar_data.dataset.ray_backend import build_dataset_ray

        out = build_dataset_ray(
            args.config,
            args.out,
            address=args.address,
            actors=args.workers,
            force=args.force,
            resume=args.resume,
        )
    else:
        out = build_dataset(args.config, args.out, workers=args.workers, force=args.force, resume=args.resume)
    print(out)
    return 0


def run_validate(args: argparse.Namespace) -> int:
    from rebar_data.dataset.validate import validate_dataset

    failures = validate_dataset(dataset_folder(args.path))
    for line in failures:
        print(line)
    if failures:
        print(f"{args.path}: INVALID ({len(failures)} failures)", file=sys.stderr)
        return 1
    print(f"{args.path}: valid")
    return 0


AUDIT_COMMAND = "rebar dataset audit"


def audit_out(path: Path, out: str | None) -> Path:
    """Where the audit of the dataset ``path`` writes its report: ``--out`` (new, empty or an earlier audit's
    output), else the dataset's own ``audit/``, which must then be writable (a read-only dataset is told to
    give ``--out``). Checked before any work."""
    from rebar_data.outputs import output_folder

    if out is not None:
        return output_folder(out, arg="--out", command=AUDIT_COMMAND, owned=_is_audit_report)
    own = path / layout.AUDIT_DIR
    writable = os.access(own, os.W_OK | os.X_OK) if own.is_dir() else os.access(path, os.W_OK | os.X_OK)
    if not writable:
        raise ConfigError(
            f"{path}: read-only, and the audit writes its report to {own}; accepted: --out DIR to write the "
            "report elsewhere (the dataset is only read)"
        )
    return own


def _is_audit_report(folder: Path) -> bool:
    """An earlier audit's output: its report and nothing but the files an audit writes."""
    return (folder / "report.json").is_file() and all(
        p.suffix in (".json", ".md", ".png") for p in folder.iterdir()
    )


def run_audit(args: argparse.Namespace) -> int:
    from rebar_data.dataset.audit import audit_dataset, result_word
    from rebar_data.dataset.layout import DatasetFormatError

    path = dataset_folder(args.path)
    out = audit_out(path, args.out)
    try:
        checks, _ = audit_dataset(path, out=out)
    except DatasetFormatError as e:
        raise ConfigError(str(e)) from None
    for c in checks:
        print(f"{result_word(c.passed, c.applicable):4}  {c.name}: {c.value:.6g} (bar {c.bar}) - {c.detail}")
    failed = [c.name for c in checks if not c.passed]
    print(f"report: {out / 'report.md'}")
    if failed:
        print(f"{args.path}: audit FAILED: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


def register(sub: argparse._SubParsersAction) -> argparse._SubParsersAction:
    d = sub.add_parser("dataset", help="build, validate, audit, publish and compare datasets")
    dsub = d.add_subparsers(dest="dataset_command", required=True)
    b = dsub.add_parser("build", help="render and label a dataset; prints its folder last")
    b.add_argument("config", help="pipeline YAML, such as pipelines/paper-tunnel.yaml")
    b.add_argument("--out", required=True, help="root folder; the dataset goes to OUT/<name>/v<version>")
    b.add_argument(
        "--workers",
        type=int,
        default=None,
        help=f"worker processes, 1 to {os.cpu_count() or 1} (this machine's cores; default: all of them; "
        "one worker already keeps two cores busy); with --backend ray, Ray actors, 1 or more (default: one "
        "per CPU of the cluster)",
    )
    b.add_argument(
        "--force", action="store_true", help="rebuild a version this command built (swapped in at the end)"
    )
    b.add_argument("--resume", action="store_true", help="continue an interrupted build of the same config")
    b.add_argument(
        "--backend",
        choices=["local", "ray"],
        default="local",
        help="local: a process pool on this machine; ray: actors on a Ray cluster (pip install -e '.[ray]')",
    )
    b.add_argument(
        "--address",
        default=None,
        help="Ray cluster to join (from `ray start --head`, or auto); default: RAY_ADDRESS, else a local "
        "cluster. --out must be on a filesystem every node shares",
    )
    b.set_defaults(func=run_build)
    v = dsub.add_parser("validate", help="check every file against schemas/ and the manifest")
    v.add_argument("path")
    v.set_defaults(func=run_validate)
    a = dsub.add_parser("audit", help="label-quality checks, report and contact sheet (audit/)")
    a.add_argument("path")
    a.add_argument(
        "--out",
        default=None,
        help="folder for the report, plots and contact sheet (default: the dataset's audit/; needed for a "
        "read-only dataset)",
    )
    a.set_defaults(func=run_audit)
    return dsub
