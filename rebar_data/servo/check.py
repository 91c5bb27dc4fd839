"""``rebar servo check DIR``: hold a run's visits to the regression bars of ``eval/thresholds.yaml``.

Bars are per mode; ``default`` applies to every suite and ``suites.<name>`` overrides single bars for
one suite. Convergence counts over the visits to true crossings (a visit to no crossing must end untied);
the error and iteration bars over the converged ones (a visit that did not converge is already a failure of
the convergence bar). Errors are read from the
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

# bars on what a run may not have: tool moves (tcp.approach off), ties, a tour's clock
NOT_IN_EVERY_RUN = {
    "max_tcp_error_m",
    "max_tie_lateral_error_m",
    "max_tie_crossing_distance_m",
    "max_sim_s_per_tie",
    "max_tilt_error_deg",
    "max_jaw_error_deg",
}
NEEDED_COLUMNS = {
    "mode",
    "converged",
    "iterations",
    "final_error_px",
    "final_true_error_px",
    "final_true_lateral_error_m",
    "final_true_error_m",
    "tcp_reached",
    "tcp_error_m",
    "max_joint_position_ratio",
    "target_id",
    "final_tilt_error_deg",
    "final_jaw_error_deg",
    "tied",
    "tcp_lateral_error_m",
    "tie_tilt_error_deg",
    "tie_jaw_error_deg",
    "tie_crossing_distance_m",
}
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
    # the tie (rebar_data.servo.control.tool_move) and the tool's alignment (rebar_data.servo.alignment)
    max_tilt_error_deg: NonNegative | None = None
    max_jaw_error_deg: NonNegative | None = None
    min_tied_fraction: float | None = None
    max_tie_lateral_error_m: NonNegative | None = None
    max_tie_crossing_distance_m: NonNegative | None = None
    max_sim_s_per_tie: NonNegative | None = None
    min_covered_fraction: float | None = None  # a tour's crossings tied over the element's crossings


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
    # convergence counts over the visits to true crossings (and those that found no target): a visit to what
    # is no crossing that ends untied is the loop refusing it (a tie there fails max_tie_crossing_distance_m)
    judged = [r for r in rows if r["target_id"] >= 0 or r["reason"] == "no_target"]

    tcp = np.array([r["tcp_error_m"] for r in conv if r.get("tcp_reached")], float)
    tied = [r for r in rows if r["tied"]]

    def worst_of(values) -> float:
        a = np.array(list(values), float)
        a = a[np.isfinite(a)]
        return float(a.max()) if len(a) else float("nan")

    def worst(key: str) -> float:
        return worst_of(r[key] for r in conv)

    # the tool's alignment where it tied, else where its servo ended
    tilt = [r["tie_tilt_error_deg"] if r["tied"] else r["final_tilt_error_deg"] for r in conv]
    jaw = [r["tie_jaw_error_deg"] if r["tied"] else r["final_jaw_error_deg"] for r in conv]
    # true crossings tied over true crossings tried (a crossing tried twice counts once)
    tried = {r["target_id"] for r in rows if r["target_id"] >= 0}
    tied_ids = {r["target_id"] for r in tied if r["target_id"] >= 0}
    attempts = len(tried)
    return {
        "visits": float(len(rows)),
        "converged_fraction": sum(r["converged"] for r in judged) / len(judged) if judged else 0.0,
        "median_iterations": float(np.median([r["iterations"] for r in conv])) if conv else float("nan"),
        "final_error_px": worst("final_error_px"),
        "true_error_px": worst("final_true_error_px"),
        "true_lateral_error_m": worst("final_true_lateral_error_m"),
        "true_error_m": worst("final_true_error_m"),
        "tcp_error_m": float(tcp.max()) if len(tcp) else float("nan"),
        "joint_position_ratio": max((r["max_joint_position_ratio"] for r in rows), default=0.0),
        "tilt_error_deg": worst_of(tilt),
        "jaw_error_deg": worst_of(jaw),
        "tied_fraction": len(tied_ids) / attempts if attempts else 0.0,
        "tie_lateral_error_m": worst_of(r["tcp_lateral_error_m"] for r in tied),
        "tie_crossing_distance_m": worst_of(r["tie_crossing_distance_m"] for r in tied),
    }


def check_run(run_dir: str | Path, thresholds: Thresholds) -> tuple[list[str], list[str]]:
    """Lines describing each mode, and one line per bar that fails (empty when everything holds)."""
    run = input_folder(run_dir, arg="run", what="a folder written by `rebar servo run`")
    for name in ("episodes.parquet", "summary.json"):
        if not (run / name).exists():
            raise ConfigError(f"{run}: no {name}; accepted: a folder written by `rebar servo run`")
    try:
        summary = json.loads((run / "summary.json").read_bytes())
        suite = summary["suite"]
        rows = pq.read_table(run / "episodes.parquet").to_pylist()
    except (OSError, ValueError, KeyError, TypeError, pa.ArrowException) as e:
        raise ConfigError(
            f"{run}: its summary.json or episodes.parquet cannot be read ({type(e).__name__}); accepted: a "
            "folder written by `rebar servo run`"
        ) from None
    missing = sorted(NEEDED_COLUMNS - set(rows[0])) if rows else []
    if missing:
        raise ConfigError(
            f"{run}/episodes.parquet has no {', '.join(missing)} columns (a run of an older rebar servo); "
            "accepted: a folder written by this `rebar servo run` (run the suite again)"
        )
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
        tour = summary.get("tour")
        m["sim_s_per_tie"] = float(tour["sim_s_per_tie"]) if tour and tour.get("ties") else float("nan")
        m["covered_fraction"] = float(tour["covered_fraction"]) if tour else 0.0
        info.append(
            f"{suite} {mode}: {int(m['visits'])} visits, {m['converged_fraction']:.0%} converged, median "
            f"{m['median_iterations']:.0f} iterations, worst final {m['final_error_px']:.2f} px, worst true "
            f"lateral {m['true_lateral_error_m'] * 1000:.2f} mm, worst true error {m['true_error_m'] * 1000:.2f} mm; "
            f"tied {m['tied_fraction']:.0%}, worst tie {m['tie_lateral_error_m'] * 1000:.2f} mm, tilt "
            f"{m['tilt_error_deg']:.2f} deg, jaw {m['jaw_error_deg']:.2f} deg"
            + (f", {m['sim_s_per_tie']:.2f} s a tie" if np.isfinite(m["sim_s_per_tie"]) else "")
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
            ("max_tilt_error_deg", m["tilt_error_deg"], b.max_tilt_error_deg, "<="),
            ("max_jaw_error_deg", m["jaw_error_deg"], b.max_jaw_error_deg, "<="),
            ("min_tied_fraction", m["tied_fraction"], b.min_tied_fraction, ">="),
            ("max_tie_lateral_error_m", m["tie_lateral_error_m"], b.max_tie_lateral_error_m, "<="),
            (
                "max_tie_crossing_distance_m",
                m["tie_crossing_distance_m"],
                b.max_tie_crossing_distance_m,
                "<=",
            ),
            ("max_sim_s_per_tie", m["sim_s_per_tie"], b.max_sim_s_per_tie, "<="),
            ("min_covered_fraction", m["covered_fraction"], b.min_covered_fraction, ">="),
        ]
        for name, value, bar, op in checks:
            if bar is None:
                continue
            ok = np.isfinite(value) and (value >= bar if op == ">=" else value <= bar)
            if name in NOT_IN_EVERY_RUN and not np.isfinite(value):
                ok = True  # none in this run (no tool moves, ties or tour): min_tied_fraction judges that
            if not ok:
                failures.append(f"{suite} {mode}: {name[4:]} = {value:.4g}, bar {op} {bar:g}")
    return info, failures
