"""Summary figures and ``report.md``: tables in the form of the paper's Tables 1 and 2, convergence plots
like its Figures 13 and 14 (camera views at the start and at each convergence, error against iteration).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from rebar_data.servo.config import SuiteConfig

CONTROL_MODES = ("ibvs", "pbvs")


def _finite(values) -> np.ndarray:
    a = np.asarray([v for v in values if v is not None], float)
    return a[np.isfinite(a)]


def _stat(values, fn) -> float | None:
    a = _finite(values)
    return float(fn(a)) if len(a) else None


def summarize(visits: list[dict]) -> dict:
    """Per-mode figures over the visits (errors over converged visits, convergence over all)."""
    out: dict = {"visits": len(visits), "modes": {}}
    for mode in CONTROL_MODES:
        g = [v for v in visits if v["mode"] == mode]
        if not g:
            continue
        conv = [v for v in g if v["converged"]]
        tcp = [v for v in conv if v["tcp_reached"]]
        out["modes"][mode] = {
            "visits": len(g),
            "converged": len(conv),
            "converged_fraction": len(conv) / len(g),
            "reasons": dict(Counter(v["reason"] for v in g)),
            "median_iterations": _stat([v["iterations"] for v in conv], np.median),
            "max_iterations": _stat([v["iterations"] for v in conv], np.max),
            "median_initial_error_px": _stat([v["initial_error_px"] for v in g], np.median),
            "max_final_error_px": _stat([v["final_error_px"] for v in conv], np.max),
            "median_final_error_px": _stat([v["final_error_px"] for v in conv], np.median),
            "max_final_true_error_px": _stat([v["final_true_error_px"] for v in conv], np.max),
            "max_final_true_lateral_error_m": _stat([v["final_true_lateral_error_m"] for v in conv], np.max),
            "median_final_true_lateral_error_m": _stat(
                [v["final_true_lateral_error_m"] for v in conv], np.median
            ),
            "max_final_true_error_m": _stat([v["final_true_error_m"] for v in conv], np.max),
            "median_final_true_error_m": _stat([v["final_true_error_m"] for v in conv], np.median),
            "median_initial_error_m": _stat([v["initial_error_m"] for v in g], np.median),
            "tcp_visits": len(tcp),
            "max_tcp_error_m": _stat([v["tcp_error_m"] for v in tcp], np.max),
            "median_tcp_error_m": _stat([v["tcp_error_m"] for v in tcp], np.median),
            "max_joint_position_ratio": _stat([v["max_joint_position_ratio"] for v in g], np.max),
            "max_joint_speed_ratio": _stat([v["max_joint_speed_ratio"] for v in g], np.max),
            "median_wall_s": _stat([v["wall_s"] for v in g], np.median),
        }
    return out


def _fmt(x, scale: float = 1.0, digits: int = 2) -> str:
    if x is None or not np.isfinite(x):
        return "-"
    return f"{x * scale:.{digits}f}"


def _table(visits: list[dict], mode: str, limit: int) -> list[str]:
    g = [v for v in visits if v["mode"] == mode]
    if mode == "ibvs":
        head = "| Target | Initial error (px) | Final error (px) | True final error (px) | True lateral error (mm) | Iterations to converge | Tool error (mm) | Result |"
    else:
        head = "| Target | Initial error (cm) | Final error (cm) | True final error (cm) | True lateral error (mm) | Iterations to converge | Tool error (mm) | Result |"
    lines = [head, "|" + " --- |" * 8]
    for v in g[:limit]:
        name = f"E{v['episode']} T{v['visit'] + 1}"
        if mode == "ibvs":
            a, b, c = _fmt(v["initial_error_px"]), _fmt(v["final_error_px"]), _fmt(v["final_true_error_px"])
        else:
            a, b, c = (_fmt(v[k], 100) for k in ("initial_error_m", "final_error_m", "final_true_error_m"))
        lines.append(
            f"| {name} | {a} | {b} | {c} | {_fmt(v['final_true_lateral_error_m'], 1000)} | {v['iterations']} | "
            f"{_fmt(v['tcp_error_m'], 1000)} | {v['reason']} |"
        )
    if len(g) > limit:
        lines.append(f"| ... {len(g) - limit} more in episodes.parquet | | | | | | | |")
    return lines


def _plot_errors(steps: list[dict], mode: str, path: Path) -> bool:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [s for s in steps if s["mode"] == mode and s["phase"] == "servo" and np.isfinite(s["error_px"])]
    if not rows:
        return False
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    visits = sorted({(s["episode"], s["visit"]) for s in rows})
    many = len(visits) > 12
    for ep, k in visits:
        g = [s for s in rows if s["episode"] == ep and s["visit"] == k]
        it = [s["iteration"] for s in g]
        label = None if many else f"E{ep} T{k + 1}"
        kw = {"lw": 0.8, "alpha": 0.5} if many else {"lw": 1.5}
        if mode == "ibvs":
            axes[0].semilogy(it, np.maximum([s["error_px"] for s in g], 1e-3), label=label, **kw)
            axes[1].semilogy(
                it, np.maximum([s["true_lateral_error_m"] * 1000 for s in g], 1e-3), label=label, **kw
            )
        else:
            axes[0].semilogy(it, np.maximum([s["error_m"] * 100 for s in g], 1e-4), label=label, **kw)
            axes[1].semilogy(it, np.maximum([s["true_error_m"] * 1000 for s in g], 1e-3), label=label, **kw)
    if mode == "ibvs":
        axes[0].set(title="IBVS: image error (tracked point)", xlabel="iteration", ylabel="error (px)")
        axes[0].axhline(1.0, color="k", ls="--", lw=0.8)
        axes[1].set(title="IBVS: true lateral error", xlabel="iteration", ylabel="error (mm)")
        axes[1].axhline(1.0, color="k", ls="--", lw=0.8)
    else:
        axes[0].set(title="PBVS: 3D error (measured)", xlabel="iteration", ylabel="error (cm)")
        axes[1].set(title="PBVS: true 3D error", xlabel="iteration", ylabel="error (mm)")
        axes[1].axhline(2.0, color="k", ls="--", lw=0.8)
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        if not many:
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def _plot_paths(steps: list[dict], mode: str, path: Path, width: int, height: int) -> bool:
    """Image-space paths of the tracked points (the paper's 'initial feature positions' to 'converged')."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [s for s in steps if s["mode"] == mode and s["phase"] == "servo" and np.isfinite(s["feature_u"])]
    if not rows:
        return False
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    visits = sorted({(s["episode"], s["visit"]) for s in rows})
    for ep, k in visits[:40]:
        g = [s for s in rows if s["episode"] == ep and s["visit"] == k]
        u, v = [s["feature_u"] for s in g], [s["feature_v"] for s in g]
        line = ax.plot(u, v, lw=1.2)[0]
        ax.plot(u[0], v[0], "o", color=line.get_color(), ms=5)
        if len(visits) <= 12:
            ax.annotate(f"T{k + 1}", (u[0], v[0]), textcoords="offset points", xytext=(4, 4), fontsize=8)
    d = rows[0]
    ax.plot(d["desired_u"], d["desired_v"], "+", color="magenta", ms=16, mew=2, label="desired")
    ax.set(
        xlim=(0, width),
        ylim=(height, 0),
        aspect="equal",
        xlabel="u (px)",
        ylabel="v (px)",
        title=f"{mode.upper()}: tracked crossing in the image, start (dot) to desired (+)",
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def write_snapshots(snapshots: list[tuple[str, np.ndarray]], path: Path) -> bool:
    """Side-by-side camera views (already annotated), captioned, as one PNG."""
    if not snapshots:
        return False
    tiles = []
    for title, img in snapshots[:5]:
        t = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
        t = cv2.copyMakeBorder(t, 24, 4, 4, 4, cv2.BORDER_CONSTANT, value=(255, 255, 255))
        cv2.putText(t, title, (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        tiles.append(t)
    cv2.imwrite(str(path), np.hstack(tiles)[..., ::-1])
    return True


def write_report(
    suite: SuiteConfig,
    visits: list[dict],
    steps: list[dict],
    out: Path,
    summary: dict,
    snapshots: dict[str, list[tuple[str, np.ndarray]]] | None = None,
) -> None:
    """``report.md`` and its figures in ``out``."""
    w, h = summary["camera"]["width"], summary["camera"]["height"]
    fx = summary["camera"]["fx"]
    lines = [
        f"# Servo suite `{suite.name}`",
        "",
        f"Detector `{suite.detector}`, frames `{suite.frames}`, faults: {visits[0]['faults'] if visits else 'none'}; "
        f"camera {w}x{h}, fx = fy = {fx:.1f} px ({summary['camera']['fov_deg'][0]:.1f} x "
        f"{summary['camera']['fov_deg'][1]:.1f} deg); controller period {suite.world.control_period_s * 1000:.0f} ms, "
        f'physics {suite.world.physics_hz:.0f} Hz. "True" values come from the simulator, not the detector.',
        "",
        "## Summary",
        "",
        "| Mode | Visits | Converged | Median iterations | Max final error (px) | Max true lateral error (mm) | Max true error (mm) | Median tool error (mm) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for mode, m in summary["modes"].items():
        lines.append(
            f"| {mode.upper()} | {m['visits']} | {m['converged']} ({m['converged_fraction']:.0%}) | "
            f"{_fmt(m['median_iterations'], digits=0)} | {_fmt(m['max_final_error_px'])} | "
            f"{_fmt(m['max_final_true_lateral_error_m'], 1000)} | {_fmt(m['max_final_true_error_m'], 1000)} | "
            f"{_fmt(m['median_tcp_error_m'], 1000)} |"
        )
    lines.append("")
    for mode, number in (("ibvs", 1), ("pbvs", 2)):
        if mode not in summary["modes"]:
            continue
        what = "IBVS convergence (image space)" if mode == "ibvs" else "PBVS convergence (Cartesian)"
        lines += [f"## Table {number}. {what}", ""] + _table(visits, mode, 24) + [""]
        if _plot_errors(steps, mode, out / f"{mode}_convergence.png"):
            lines += [f"![{mode} convergence]({mode}_convergence.png)", ""]
        if _plot_paths(steps, mode, out / f"{mode}_image_paths.png", w, h):
            lines += [f"![{mode} image paths]({mode}_image_paths.png)", ""]
        if snapshots and write_snapshots(snapshots.get(mode, []), out / f"{mode}_views.png"):
            lines += [
                f"Camera views of the first {mode.upper()} episode: the targets at the start, then each at convergence.",
                "",
                f"![{mode} views]({mode}_views.png)",
                "",
            ]
    lines += [
        "Reasons a visit ends: `converged`, `diverged` (error grew past the safety factor), `lost` (target not "
        "seen for too long; the arm held still meanwhile), `timeout`, `collision`, `no_target`.",
        "",
    ]
    (out / "report.md").write_text("\n".join(lines))
