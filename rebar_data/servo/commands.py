"""`rebar servo run SUITE --out DIR` and `rebar servo check DIR`."""

from __future__ import annotations

import argparse
import sys

from rebar_data.arguments import bounded

EPISODES = bounded(int, 1)


def run_servo(args: argparse.Namespace) -> int:
    from rebar_data.servo.run import run_suite

    summary = run_suite(args.suite, args.out, progress=not args.quiet, limit_episodes=args.episodes)
    for mode, m in summary["modes"].items():
        it = m["median_iterations"]
        lat = m["max_final_true_lateral_error_m"]
        print(
            f"{summary['suite']} {mode}: {m['converged']}/{m['visits']} converged, median "
            f"{'-' if it is None else f'{it:.0f}'} iterations, worst true lateral error "
            f"{'-' if lat is None else f'{lat * 1000:.2f}'} mm",
            file=sys.stderr,
        )
    print(args.out)
    return 0


def run_check(args: argparse.Namespace) -> int:
    from rebar_data.servo.check import check_run, load_thresholds

    info, failures = check_run(args.run, load_thresholds(args.thresholds))
    for line in info:
        print(line)
    for line in failures:
        print(f"REGRESSION {line}")
    print("servo check: " + ("ok" if not failures else f"{len(failures)} regression(s)"))
    return 1 if failures else 0


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("servo", help="visual servoing evaluation in simulation (IBVS, PBVS)")
    ss = s.add_subparsers(dest="servo_command", required=True)
    r = ss.add_parser(
        "run", help="run a suite: episodes.parquet, steps.parquet, summary.json, report.md, .rrd"
    )
    r.add_argument("suite", help="suite YAML, such as eval/ci.yaml")
    r.add_argument(
        "--out",
        required=True,
        help="output folder: new, empty, or an earlier run's, which is replaced whole (any other folder is "
        "refused)",
    )
    r.add_argument(
        "--episodes", type=EPISODES, default=None, help=f"run only the first N episodes (N: {EPISODES})"
    )
    r.add_argument("--quiet", action="store_true", help="no progress lines")
    r.set_defaults(func=run_servo)
    c = ss.add_parser("check", help="compare a run with the regression bars; exit 1 on a regression")
    c.add_argument("run", help="a folder written by `rebar servo run`")
    c.add_argument("--thresholds", default=None, help="bars file (default eval/thresholds.yaml)")
    c.set_defaults(func=run_check)
