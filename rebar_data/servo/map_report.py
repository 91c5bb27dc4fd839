"""A servo map's outputs: its table (``map.parquet``, ``map.csv``), ``summary.json``, ``map.md`` and ``map.png``.

The PNG draws each (mode, turn) as a row of three panels on the unrolled surface (axial distance from the crown
across, arc distance up): the share of the cell's views that converged, their median iterations, and the worst
true lateral error of those that did. A surface point no view could reach from the base is left grey and
marked x: out of the arm's reach, or an arm link in the floor, the table or the mesh at the start.
"""

from __future__ import annotations

import json
import math
import platform
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import rebar_data
from rebar_data.servo.config import SuiteConfig


def _finite(values) -> list[float]:
    return [float(v) for v in values if v is not None and math.isfinite(float(v))]


def _group_figures(rows: list[dict]) -> dict:
    reach = [r for r in rows if r["reachable"]]
    conv = [r for r in reach if r["converged"]]
    it = _finite(r["iterations"] for r in conv)
    lat = _finite(r["lateral_error_m"] for r in conv)
    tilt = _finite(r["tilt_error_deg"] for r in conv)
    jaw = _finite(r["jaw_error_deg"] for r in conv)
    reasons: dict[str, int] = {}
    for r in reach:
        reasons[r["reason"]] = reasons.get(r["reason"], 0) + 1
    return {
        "cells": len(rows),
        "reachable": len(reach),
        "converged": len(conv),
        "converged_share_of_reachable": len(conv) / len(reach) if reach else None,
        "reasons": reasons,
        "median_iterations": float(np.median(it)) if it else None,
        "max_iterations": max(it) if it else None,
        "max_lateral_error_m": max(lat) if lat else None,
        "median_lateral_error_m": float(np.median(lat)) if lat else None,
        "max_tilt_error_deg": max(tilt) if tilt else None,
        "max_jaw_error_deg": max(jaw) if jaw else None,
    }


def summarize_map(suite: SuiteConfig, rows: list[dict]) -> dict:
    m = suite.map
    modes = {mode: _group_figures([r for r in rows if r["mode"] == mode]) for mode in m.modes}
    by_turn = {
        mode: {
            f"{t:g}": _group_figures([r for r in rows if r["mode"] == mode and r["turn_deg"] == t])
            for t in m.turns_deg
        }
        for mode in m.modes
    }
    return {"suite": suite.name, "cells": len(rows), "modes": modes, "turns": by_turn}


def write_map(
    suite: SuiteConfig, rows: list[dict], out: Path, *, wall_s: float, workers: int, backend: str
) -> dict:
    """Write every output of the map to ``out``; the summary."""
    from rebar_data.servo.run import json_default

    table = pa.Table.from_pylist(rows)
    pq.write_table(table, out / "map.parquet")
    table.to_pandas().to_csv(out / "map.csv", index=False)
    summary = summarize_map(suite, rows)
    summary.update(
        {
            "seed": suite.seed,
            "detector": suite.detector,
            "frames": suite.frames,
            "config": suite.model_dump(mode="json"),
            "wall_s": wall_s,
            "workers": workers,
            "backend": backend,
            "python": platform.python_version(),
            "package_version": rebar_data.__version__,
        }
    )
    (out / "summary.json").write_text(
        json.dumps(summary, indent=2, sort_keys=True, default=json_default) + "\n"
    )
    draw_map(suite, rows, out / "map.png")
    (out / "map.md").write_text(map_markdown(suite, rows, summary))
    return summary


def _mm(v) -> str:
    return "-" if v is None else f"{v * 1000:.2f}"


def _num(v, fmt: str = ".0f") -> str:
    return "-" if v is None else format(v, fmt)


def map_markdown(suite: SuiteConfig, rows: list[dict], summary: dict) -> str:
    m = suite.map
    lines = [
        f"# Servo map: {suite.name}",
        "",
        f"Detector `{suite.detector}`, frames `{suite.frames}`, depth sensor `{suite.camera.depth_sensor}`; "
        f"{summary['cells']} cells: modes {', '.join(m.modes)} x turns {', '.join(f'{t:g}' for t in m.turns_deg)} "
        f"deg x {len(m.views)} views x {m.axial_steps} x {m.arc_steps} surface points "
        f"(axial {m.axial_m[0]:g} to {m.axial_m[1]:g} m, arc {m.arc_m[0]:g} to {m.arc_m[1]:g} m), "
        f"{m.targets} target(s) a cell from {m.standoff_m:g} m. Wall time {summary['wall_s']:.0f} s on "
        f"{summary['workers']} {summary['backend']} worker(s).",
        "",
        "![map](map.png)",
        "",
        "| mode | turn (deg) | view (tilt x, tilt y, roll deg) | reachable | converged | median iterations | "
        "worst lateral (mm) | worst tilt (deg) | worst jaw (deg) | not converged |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for mode in m.modes:
        for t in m.turns_deg:
            for vi, v in enumerate(m.views):
                g = [r for r in rows if r["mode"] == mode and r["turn_deg"] == t and r["view"] == vi]
                f = _group_figures(g)
                others = ", ".join(f"{k} {n}" for k, n in sorted(f["reasons"].items()) if k != "converged")
                lines.append(
                    f"| {mode} | {t:g} | {v.tilt_deg[0]:g}, {v.tilt_deg[1]:g}, {v.roll_deg:g} | "
                    f"{f['reachable']}/{f['cells']} | {f['converged']}/{f['reachable']} | "
                    f"{_num(f['median_iterations'])} | {_mm(f['max_lateral_error_m'])} | "
                    f"{_num(f['max_tilt_error_deg'], '.2f')} | {_num(f['max_jaw_error_deg'], '.2f')} | "
                    f"{others or '-'} |"
                )
    lines += ["", "Rows: `map.parquet` / `map.csv`, one a cell (its start, outcome and true errors).", ""]
    return "\n".join(lines)


def _surface_grid(rows: list[dict], axial: list[float], arc: list[float]) -> dict[str, np.ndarray]:
    """Per surface point over the views: converged share of the reachable, median iterations and worst
    lateral error (mm) of the converged; NaN where no view was reachable."""
    shape = (len(arc), len(axial))
    share, iters, worst = (np.full(shape, np.nan) for _ in range(3))
    for i, s in enumerate(arc):
        for j, a in enumerate(axial):
            g = [r for r in rows if r["axial_m"] == a and r["arc_m"] == s and r["reachable"]]
            if not g:
                continue
            conv = [r for r in g if r["converged"]]
            share[i, j] = len(conv) / len(g)
            it = _finite(r["iterations"] for r in conv)
            lat = _finite(r["lateral_error_m"] for r in conv)
            iters[i, j] = np.median(it) if it else np.nan
            worst[i, j] = 1000 * max(lat) if lat else np.nan
    return {"share": share, "iterations": iters, "lateral_mm": worst}


def _label(name: str, v: float) -> str:
    return f"{100 * v:.0f}%" if name == "share" else f"{v:.0f}" if name == "iterations" else f"{v:.2f}"


def _ink(name: str, x: float) -> str:
    """Text colour on a panel's colour at ``x`` (0-1 along its scale): white where that colour is dark."""
    dark = {"share": x < 0.2 or x > 0.8, "iterations": x < 0.5, "lateral_mm": x > 0.55}[name]
    return "white" if dark else "black"


def draw_map(suite: SuiteConfig, rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = suite.map
    axial = sorted({r["axial_m"] for r in rows})
    arc = sorted({r["arc_m"] for r in rows})
    panels = [(mode, t) for t in m.turns_deg for mode in m.modes]
    fig, axes = plt.subplots(len(panels), 3, figsize=(12.5, 3.4 * len(panels)), squeeze=False)
    da = (axial[1] - axial[0]) / 2 if len(axial) > 1 else 0.05
    ds = (arc[1] - arc[0]) / 2 if len(arc) > 1 else 0.05
    extent = (axial[0] - da, axial[-1] + da, arc[0] - ds, arc[-1] + ds)
    all_it = _finite(r["iterations"] for r in rows if r["converged"])
    all_lat = _finite(1000 * r["lateral_error_m"] for r in rows if r["converged"])
    top_mm = max(1.0, max(all_lat)) if all_lat else 1.0
    scales = {
        "share": (0.0, 1.0, "RdYlGn", "converged (of views reached)"),
        "iterations": (0.0, max(all_it) if all_it else 1.0, "viridis", "median iterations"),
        "lateral_mm": (0.0, top_mm, "magma_r", "worst lateral error (mm)"),
    }
    for row_axes, (mode, t) in zip(axes, panels, strict=True):
        g = [r for r in rows if r["mode"] == mode and r["turn_deg"] == t]
        grids = _surface_grid(g, axial, arc)
        for ax, (name, (lo, hi, cmap, label)) in zip(row_axes, scales.items(), strict=True):
            cm = plt.get_cmap(cmap).with_extremes(bad="#bbbbbb")
            im = ax.imshow(
                np.ma.masked_invalid(grids[name]),
                origin="lower",
                extent=extent,
                cmap=cm,
                vmin=lo,
                vmax=hi,
                aspect="equal",
                interpolation="nearest",
            )
            for i, s in enumerate(arc):
                for j, a in enumerate(axial):
                    here = [r for r in g if r["axial_m"] == a and r["arc_m"] == s]
                    reached = sum(bool(r["reachable"]) for r in here)
                    if not reached:
                        ax.plot(a, s, "x", color="#555555", ms=6)
                    elif np.isfinite(v := grids[name][i, j]) and len(axial) * len(arc) <= 81:
                        text = _label(name, v)
                        if name == "share" and reached < len(here):  # some views out of reach there
                            text += f"\n{reached}/{len(here)} views"
                        x = (v - lo) / max(hi - lo, 1e-9)
                        ax.text(a, s, text, ha="center", va="center", fontsize=6.5, color=_ink(name, x))
            ax.set_title(f"{mode.upper()}, turned {t:g} deg: {label}", fontsize=9)
            ax.set_xlabel("along the axis from the crown (m)", fontsize=8)
            ax.set_ylabel("along the arc (m)", fontsize=8)
            ax.tick_params(labelsize=7)
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03).ax.tick_params(labelsize=7)
    views = f"{len(m.views)} view{'s' if len(m.views) > 1 else ''} a surface point"
    base = "the base moved to each point" if m.base == "follow" else "the base fixed"
    fig.suptitle(
        f"Servo map: {suite.name} ({views}, {base}; true errors from the simulator)\ngrey x: out of the arm's "
        "reach, or an arm link in the floor, the table or the mesh",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
