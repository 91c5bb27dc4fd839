"""`rebar servo run SUITE --out DIR`, `rebar servo check DIR` and `rebar servo map SUITE --out DIR`."""

from __future__ import annotations

import argparse
import os
import sys

from rebar_data.arguments import bounded

EPISODES = bounded(int, 1)


def _per_mode(summary: dict, line) -> None:
    """One line a mode of a run's or a map's summary: ``line(figures)`` after the suite and the mode."""
    for mode, m in summary["modes"].items():
        print(f"{summary['suite']} {mode}: {line(m)}", file=sys.stderr)


def _or_dash(value: float | None, scale: float, fmt: str) -> str:
    return "-" if value is None else format(value * scale, fmt)


def run_servo(args: argparse.Namespace) -> int:
    from rebar_data.servo.run import run_suite

    summary = run_suite(args.suite, args.out, progress=not args.quiet, limit_episodes=args.episodes)
    _per_mode(
        summary,
        lambda m: (
            f"{m['converged']}/{m['visits']} converged, median {_or_dash(m['median_iterations'], 1, '.0f')} "
            f"iterations, worst true lateral error {_or_dash(m['max_final_true_lateral_error_m'], 1000, '.2f')} mm"
        ),
    )
    print(args.out)
    return 0


def run_map_command(args: argparse.Namespace) -> int:
    from rebar_data.servo.servo_map import run_map

    summary = run_map(
        args.suite,
        args.out,
        workers=args.workers,
        backend=args.backend,
        address=args.address,
        progress=not args.quiet,
    )
    _per_mode(
        summary,
        lambda m: (
            f"{m['reachable']}/{m['cells']} cells reachable, {m['converged']} converged "
            f"({_or_dash(m['converged_share_of_reachable'], 1, '.0%')}), worst true lateral error "
            f"{_or_dash(m['max_lateral_error_m'], 1000, '.2f')} mm"
        ),
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
    m = ss.add_parser(
        "map",
        help="sweep start poses over the element and its turns (the suite's map section): map.parquet, map.csv, "
        "map.md, map.png; resumes where it stopped",
    )
    m.add_argument("suite", help="suite YAML with a map section, such as eval/map-paper.yaml")
    m.add_argument(
        "--out", required=True, help="output folder: new, empty, or an earlier map's, which is replaced whole"
    )
    m.add_argument(
        "--workers",
        type=EPISODES,
        default=1,
        help=f"local worker processes (one renderer each), at most this machine's {os.cpu_count() or 1} cores, or "
        f"Ray actors with --backend ray ({EPISODES}; default 1)",
    )
    m.add_argument(
        "--backend", choices=("local", "ray"), default="local", help="local processes or a Ray cluster"
    )
    m.add_argument(
        "--address",
        default=None,
        help="the Ray cluster to join (HOST:PORT or auto; default: a private local one)",
    )
    m.add_argument("--quiet", action="store_true", help="no progress bar")
    m.set_defaults(func=run_map_command)
