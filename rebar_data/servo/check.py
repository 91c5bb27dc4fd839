"""``rebar servo check DIR``: hold a run's visits to the regression bars of ``eval/thresholds.yaml``.

Bars are per mode; ``default`` applies to every suite and ``suites.<name>`` overrides single bars for
one suite. Convergence counts over all visits; the error and iteration bars over the converged ones
(a visit that did not converge is already a failure of the convergence bar). Errors are read from the
simulator's ground truth where the bar says ``true``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from rebar_data.config import ConfigError, NonNegative, Strict, read_yaml, validate
from rebar_data.outputs import input_folder

DEFAULT_THRESHOLDS = Path(__file__).resolve().parents[2] / "eval" / "thresholds.yaml"


class ModeBars(Strict):
    min_visits: int | None = None
    min_converged_fraction: float | None = None
    max_median_iterations: NonNegative | None = None
    max_final_error_px: NonNegative | None = None
    max_true_error_px: NonNegative | None = None
    max_true_lateral_error_m: NonNegative | None = None
    max_true_error_m: NonNegative | None = None
    max_tcp_error_m: NonNegative | None = None
    max_joint_position_ratio: NonNegative | None = None


class SuiteBars(Strict):
    ibvs: ModeBars = ModeBars()
    pbvs: ModeBars = ModeBars()


class Thresholds(Strict):
    default: SuiteBars = SuiteBars()
    suites: dict[str, SuiteBars] = {}

    def for_suite(self, name: str) -> SuiteBars:
        """The default bars with the suite's own overrides on top."""
        own = self.suites.get(name)
        if own is None:
            return self.default
        merged = {}
        for mode in ("ibvs", "pbvs"):
            base = getattr(self.default, mode).model_dump()
            base.update(getattr(own, mode).model_dump(exclude_unset=True))
            merged[mode] = ModeBars(**base)
        return SuiteBars(**merged)


def load_thresholds(path: str | Path | None = None) -> Thresholds:
    """The bars in ``path``; by default ``eval/thresholds.yaml`` of the working folder, else of the project."""
    if path is not None:
        p = Path(path)
    else:
        p = Path("eval/thresholds.yaml") if Path("eval/thresholds.yaml").exists() else DEFAULT_THRESHOLDS
    return validate(Thresholds, read_yaml(p), str(p))


def _measures(rows: list[dict]) -> dict[str, float]:
    conv = [r for r in rows if r["converged"]]

    def worst(key: str) -> float:
        a = np.array([r[key] for r in conv], float)
        a = a[np.isfinite(a)] if len(a) else a
        return float(a.max()) if len(a) else float("nan")

    tcp = np.array([r["tcp_error_m"] for r in conv if r.get("tcp_reached")], float)
    return {
        "visits": float(len(rows)),
        "converged_fraction": len(conv) / len(rows) if rows else 0.0,
        "median_iterations": float(np.median([r["iterations"] for r in conv])) if conv else float("nan"),
        "final_error_px": worst("final_error_px"),
        "true_error_px": worst("final_true_error_px"),
        "true_lateral_error_m": worst("final_true_lateral_error_m"),
        "true_error_m": worst("final_true_error_m"),
        "tcp_error_m": float(tcp.max()) if len(tcp) else float("nan"),
        "joint_position_ratio": max((r["max_joint_position_ratio"] for r in rows), default=0.0),
    }


def check_run(run_dir: str | Path, thresholds: Thresholds) -> tuple[list[str], list[str]]:
    """Lines describing each mode, and one line per bar that fails (empty when everything holds)."""
    run = input_folder(run_dir, arg="run", what="a folder written by `rebar servo run`")
    for name in ("episodes.parquet", "summary.json"):
        if not (run / name).exists():
            raise ConfigError(f"{run}: no {name}; accepted: a folder written by `rebar servo run`")
    try:
        suite = json.loads((run / "summary.json").read_bytes())["suite"]
        rows = pq.read_table(run / "episodes.parquet").to_pylist()
    except (OSError, ValueError, KeyError, TypeError, pa.ArrowException) as e:
        raise ConfigError(
            f"{run}: its summary.json or episodes.parquet cannot be read ({type(e).__name__}); accepted: a "
            "folder written by `rebar servo run`"
        ) from None
    bars = thresholds.for_suite(suite)
    info, failures = [], []
    for mode in ("ibvs", "pbvs"):
        b: ModeBars = getattr(bars, mode)
        g = [r for r in rows if r["mode"] == mode]
        if not g:
            if b.min_visits:
                failures.append(f"{suite} {mode}: no visits, at least {b.min_visits} expected")
            continue
        m = _measures(g)
        info.append(
            f"{suite} {mode}: {int(m['visits'])} visits, {m['converged_fraction']:.0%} converged, median "
            f"{m['median_iterations']:.0f} iterations, worst final {m['final_error_px']:.2f} px, worst true "
            f"lateral {m['true_lateral_error_m'] * 1000:.2f} mm, worst true error {m['true_error_m'] * 1000:.2f} mm"
        )
        checks = [
            ("min_visits", m["visits"], b.min_visits, ">="),
            ("min_converged_fraction", m["converged_fraction"], b.min_converged_fraction, ">="),
            ("max_median_iterations", m["median_iterations"], b.max_median_iterations, "<="),
            ("max_final_error_px", m["final_error_px"], b.max_final_error_px, "<="),
            ("max_true_error_px", m["true_error_px"], b.max_true_error_px, "<="),
            ("max_true_lateral_error_m", m["true_lateral_error_m"], b.max_true_lateral_error_m, "<="),
            ("max_true_error_m", m["true_error_m"], b.max_true_error_m, "<="),
            ("max_tcp_error_m", m["tcp_error_m"], b.max_tcp_error_m, "<="),
            ("max_joint_position_ratio", m["joint_position_ratio"], b.max_joint_position_ratio, "<="),
        ]
        for name, value, bar, op in checks:
            if bar is None:
                continue
            ok = np.isfinite(value) and (value >= bar if op == ">=" else value <= bar)
            if name == "max_tcp_error_m" and not np.isfinite(value):
                ok = True  # no tool moves in this run
            if not ok:
                failures.append(f"{suite} {mode}: {name[4:]} = {value:.4g}, bar {op} {bar:g}")
    return info, failures
