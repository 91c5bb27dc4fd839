"""`rebar bench`: every stage's benchmark, each printing figures and ratios measured in the same run."""

from __future__ import annotations

import argparse
import importlib
import sys
import time

SECTIONS = {
    "mesh": "rebar_data.geometry.bench",
    "render": "rebar_data.render.bench",
    "dataset": "rebar_data.dataset.bench",
    "detector": "rebar_data.perception.evaluation.bench",
    "servo": "rebar_data.servo.bench",
}


def run_bench(args: argparse.Namespace) -> int:
    from rebar_data.timing import machine_description

    names = args.only or list(SECTIONS)
    failed = []
    print(f"machine: {machine_description()}", flush=True)  # what every figure below was timed on
    for name in names:
        t = time.perf_counter()
        print(f"== {name}", flush=True)
        try:
            module = importlib.import_module(SECTIONS[name])
        except ModuleNotFoundError as e:
            print(f"   skipped: {e}")
            continue
        try:
            for line in module.run():
                print(f"   {line}", flush=True)
        except Exception as e:  # a broken section must not hide the others' figures
            failed.append(name)
            print(f"   FAILED: {type(e).__name__}: {e}", flush=True)
        print(f"   ({time.perf_counter() - t:.0f} s)", flush=True)
    if failed:
        print(f"bench sections failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    b = sub.add_parser("bench", help="benchmarks of every stage (figures and same-run ratios)")
    b.add_argument("--only", nargs="+", choices=list(SECTIONS), help="run only these sections")
    b.set_defaults(func=run_bench)
