"""``rebar dataset publish`` and ``rebar dataset diff`` (registered under ``rebar dataset``)."""

from __future__ import annotations

import argparse
import json
import sys

from rebar_data.dataset.commands import dataset_folder


def run_publish(args: argparse.Namespace) -> int:
    from rebar_data.publish.bundle import publish_dataset

    out = publish_dataset(
        dataset_folder(args.path),
        args.out,
        license_id=args.license,
        maps=args.maps,
        force=args.force,
        allow_failed_audit=args.allow_failed_audit,
    )
    print(out)
    return 0


def run_diff(args: argparse.Namespace) -> int:
    from rebar_data.publish.diff import diff_datasets

    d = diff_datasets(dataset_folder(args.old), dataset_folder(args.new))
    print(json.dumps(d.to_dict(), indent=2, sort_keys=True, default=str) if args.json else d.report())
    if args.check and not d.declared_enough:
        print(
            f"version {d.new_version} is a {d.declared} bump over {d.old_version}; the changes need a {d.bump} bump",
            file=sys.stderr,
        )
        return 1
    return 0


def add_commands(dsub: argparse._SubParsersAction) -> None:
    """Add ``publish`` and ``diff`` to the ``rebar dataset`` sub-commands."""
    from rebar_data.publish.card import LICENSES

    p = dsub.add_parser(
        "publish",
        help="release bundle: HF Parquet with images, dataset card, Croissant, YOLO/COCO, checksums",
    )
    p.add_argument(
        "path", help="a built dataset folder such as data/smoke/v0.1.0 (validated and audited first)"
    )
    p.add_argument(
        "--out",
        required=True,
        help="folder to write the bundle to (printed last): new, empty, or an earlier bundle with --force",
    )
    p.add_argument("--license", default="cc-by-4.0", choices=list(LICENSES), help="license of the data")
    p.add_argument("--maps", action="store_true", help="also ship the depth and instance maps")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace --out when it holds an earlier bundle (a folder holding anything else is refused)",
    )
    p.add_argument(
        "--allow-failed-audit",
        action="store_true",
        help="publish even when the audit fails (the card says so)",
    )
    p.set_defaults(func=run_publish)
    d = dsub.add_parser(
        "diff", help="what changed between two versions of a dataset, and the version bump it needs"
    )
    d.add_argument("old", help="the older dataset (or bundle) folder")
    d.add_argument("new", help="the newer dataset (or bundle) folder")
    d.add_argument("--json", action="store_true", help="print the whole comparison as JSON")
    d.add_argument(
        "--check",
        action="store_true",
        help="exit 1 when NEW's version is a smaller bump than its changes need",
    )
    d.set_defaults(func=run_diff)
