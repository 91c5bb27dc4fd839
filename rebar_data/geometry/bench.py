"""Benchmark of the paper mesh build, of the analytic crossing solver against a sampling search, and of
reading IFC models (a floor plate's crossings; plates read plain and as mapped items, and a lift shaft)."""

from __future__ import annotations

import time

import numpy as np

from rebar_data.config import PAPER_PIPELINE
from rebar_data.geometry.config import MeshConfig
from rebar_data.geometry.crossings import find_crossings
from rebar_data.geometry.curves import sample
from rebar_data.geometry.solids import build_parts, merge
from rebar_data.geometry.specs import build_layout
from rebar_data.pipeline import load_mesh_config


def _timed(fn, repeat: int = 3):
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def _sampled_crossings(layout, step_m: float, reach_m: float) -> tuple[int, float]:
    """The naive alternative: sample both centerlines every ``step_m`` and take the nearest sample pair."""
    pts = [sample(b.curve, step_m)[1] for b in layout.bars]
    n = 0
    for i, a in enumerate(layout.bars):
        for j in range(i + 1, len(layout.bars)):
            if a.direction == layout.bars[j].direction:
                continue
            d = np.linalg.norm(pts[i][:, None] - pts[j][None], axis=-1).min()
            n += d <= reach_m
    return n, step_m / 2


def tiled_slab_bars(
    n_bars: int,
    *,
    panel_m: float = 5.0,
    spacing_m: float = 0.2,
    diameter_m: float = 0.012,
    mapped: bool = False,
):
    """A large floor plate as an IFC model's bars: square panels side by side (``panel_m``, 0.2 m gaps), each
    with two mats (top and bottom) of straight bars at ``spacing_m`` both ways, until ``n_bars`` bars. With
    ``mapped`` each panel's mat and direction is one placement of mapped items.

    Returns :class:`~rebar_data.geometry.ifc_write.BarRecord` s for :func:`~rebar_data.geometry.ifc_write.ifc_model`.
    Each panel crosses only itself: ``(per_panel / 4) ** 2 * 2`` crossings a whole panel.
    """
    from rebar_data.geometry.curves import Line
    from rebar_data.geometry.ifc_write import BarRecord, global_id

    per_mat_dir = int(np.floor((panel_m - 0.1) / spacing_m)) + 1
    along = (np.arange(per_mat_dir) - (per_mat_dir - 1) / 2.0) * spacing_m
    half = panel_m / 2.0 - 0.05
    columns = 10
    bars = []
    panel = 0
    while len(bars) < n_bars:
        ox, oy = (panel % columns) * (panel_m + 0.2), (panel // columns) * (panel_m + 0.2)
        for layer, z0 in enumerate((0.1, -0.1)):
            sign = 1.0 if z0 > 0 else -1.0
            for direction in (0, 1):
                z = z0 - sign * direction * diameter_m
                for u in along:
                    if len(bars) == n_bars:
                        break
                    if direction == 0:
                        a, b = np.array([ox - half, oy + u, z]), np.array([ox + half, oy + u, z])
                    else:
                        a, b = np.array([ox + u, oy - half, z]), np.array([ox + u, oy + half, z])
                    k = len(bars)
                    bars.append(
                        BarRecord(
                            k,
                            [Line(a, b)],
                            diameter_m,
                            direction,
                            layer,
                            global_id(f"bench/{n_bars}/{k}"),
                            group=f"{panel}/{layer}/{direction}" if mapped else None,
                        )
                    )
        panel += 1
    return bars


def _all_pairs_candidates(layout, pad: float) -> int:
    """The generated meshes' candidate search (every pair's padded boxes at once): pairs it keeps."""
    from rebar_data.geometry.crossings import _bounds

    boxes = [_bounds(b, b.radius_m + pad) for b in layout.bars]
    lo = np.array([bx[0] for bx in boxes]).reshape(-1, 3)
    hi = np.array([bx[1] for bx in boxes]).reshape(-1, 3)
    overlap = np.all((lo[:, None, :] <= hi[None, :, :]) & (lo[None, :, :] <= hi[:, None, :]), axis=-1)
    return int(np.triu(overlap, k=1).sum())


def _plate_figures(n_bars: int, folder) -> tuple[str, float, float, float]:
    """One floor plate written, read and crossed: its figures' line, the two candidate searches' times and the
    mesh's time (read and crossings)."""
    from rebar_data.geometry.config import IfcMesh
    from rebar_data.geometry.crossings import candidate_pairs, find_piece_crossings
    from rebar_data.geometry.ifc_read import ifc_layout
    from rebar_data.geometry.ifc_write import ifc_model

    path = folder / f"plate-{n_bars}.ifc"
    t0 = time.perf_counter()
    ifc_model(tiled_slab_bars(n_bars), file_name=path.name).write(str(path))
    t_write = time.perf_counter() - t0
    cfg = MeshConfig.model_validate({"mesh": IfcMesh(kind="ifc", ifc_path=str(path)).model_dump()})
    mesh = cfg.mesh
    t_read, layout = _timed(lambda: ifc_layout(cfg, None), repeat=1)
    t_cross, crossings = _timed(
        lambda: find_piece_crossings(layout, mesh.crossing_tolerance_m, mesh.min_crossing_angle_deg), repeat=1
    )
    pads = np.array([b.radius_m for b in layout.bars]) + mesh.crossing_tolerance_m / 2
    t_tree, (ii, _) = _timed(lambda: candidate_pairs([b.curve for b in layout.bars], pads))
    t_pairs, n_pairs = _timed(lambda: _all_pairs_candidates(layout, mesh.crossing_tolerance_m / 2), repeat=1)
    line = (
        f"IFC floor plate, {n_bars} bars ({path.stat().st_size / 1e6:.1f} MB): write {t_write:.2f} s, read "
        f"{t_read:.2f} s, crossings {t_cross:.2f} s ({len(crossings)} crossings; candidate pairs: k-d tree "
        f"{len(ii)} in {t_tree * 1e3:.0f} ms, all-pairs boxes {n_pairs} in {t_pairs * 1e3:.0f} ms)"
    )
    return line, t_tree, t_pairs, t_read + t_cross


def ifc_bench(sizes: tuple[int, ...] = (500, 2000, 5000)) -> list[str]:
    """Write a floor plate of each size to IFC, read it (``mesh.kind: ifc``) and find its crossings; how the
    mesh's time and the k-d tree candidate search grow with the bars, against the all-pairs box test."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        runs = [_plate_figures(n, Path(tmp)) for n in sizes]
    (lo, hi), ratio = (sizes[0], sizes[-1]), sizes[-1] / sizes[0]
    first, last = runs[0], runs[-1]

    def exponent(t_lo: float, t_hi: float) -> float:  # t ~ n^k over the sizes' range
        return float(np.log(t_hi / t_lo) / np.log(ratio))

    return [
        *(r[0] for r in runs),
        f"growth {lo} -> {hi} bars ({ratio:.0f}x): mesh (read and crossings) {last[3] / first[3]:.1f}x the time "
        f"(t ~ n^{exponent(first[3], last[3]):.2f}; n log n is n^{exponent(lo * np.log(lo), hi * np.log(hi)):.2f} "
        f"here), k-d tree candidate search {last[1] / first[1]:.1f}x (n^{exponent(first[1], last[1]):.2f}), "
        f"all-pairs boxes {last[2] / first[2]:.1f}x (n^{exponent(first[2], last[2]):.2f}); the k-d tree "
        f"{last[2] / last[1]:.1f}x faster at {hi}",
    ]


def run() -> list[str]:
    cfg = load_mesh_config(PAPER_PIPELINE)
    t_layout, layout = _timed(lambda: build_layout(cfg))
    t_cross, crossings = _timed(lambda: find_crossings(layout, cfg.mesh.crossing_tolerance_m))
    t_parts, parts = _timed(lambda: build_parts(layout.bars, crossings, cfg.realism, layout.rngs["tie_wire"]))
    t_merge, (mesh, _) = _timed(lambda: merge(parts))
    total = t_layout + t_cross + t_parts + t_merge
    reach = 2 * cfg.mesh.bar_diameter_m / 2 + cfg.mesh.crossing_tolerance_m
    t_naive, (n_naive, err) = _timed(lambda: _sampled_crossings(layout, 0.005, reach), repeat=1)
    return [
        f"paper mesh build: {total:.2f} s ({len(layout.bars)} bars, {len(crossings)} crossings, "
        f"{len(mesh.faces)} triangles; layout {t_layout * 1e3:.0f} ms, crossings {t_cross * 1e3:.0f} ms, "
        f"solids {t_parts * 1e3:.0f} ms, union {t_merge * 1e3:.0f} ms)",
        f"analytic crossings vs 5 mm sampling search: {t_naive / t_cross:.1f}x faster "
        f"({t_cross * 1e3:.0f} ms vs {t_naive * 1e3:.0f} ms; {len(crossings)} vs {n_naive} found; "
        f"exact to 1e-15 m vs up to {err * 1e3:.1f} mm off)",
        *_ifc_lines(),
    ]


def _rate(t: float, bars: int, pieces: int) -> str:
    return f"{bars / t:.0f} bars/s ({pieces / t:.0f} pieces/s, {t:.2f} s)"


def read_bench(sizes: tuple[int, ...] = (500, 2000, 5000), shaft_storeys: int = 31) -> list[str]:
    """Reading (``mesh.kind: ifc``: bars, faces, mats) a floor plate of each size written plain and as mapped
    items (one placement a panel's mat and direction), and the lift shaft of the Allplan class (about 5,000
    bars as mapped items, four faces): bars and pieces a second, mapped against plain."""
    import tempfile
    from pathlib import Path

    from rebar_data.geometry.config import IfcMesh
    from rebar_data.geometry.ifc_read import ifc_layout
    from rebar_data.geometry.ifc_samples import write_shaft
    from rebar_data.geometry.ifc_write import ifc_model

    def read(path: Path):
        cfg = MeshConfig.model_validate({"mesh": IfcMesh(kind="ifc", ifc_path=str(path)).model_dump()})
        t, layout = _timed(lambda: ifc_layout(cfg, None), repeat=1)
        return t, len({b.bar_id for b in layout.bars}), len(layout.bars), layout

    lines, times = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            got = {}
            for form in ("plain", "mapped"):
                path = Path(tmp) / f"plate-{n}-{form}.ifc"
                ifc_model(tiled_slab_bars(n, mapped=form == "mapped"), file_name=path.name).write(str(path))
                got[form] = read(path)
            (tp, bars, pieces, _), (tm, *_) = got["plain"], got["mapped"]
            times.append(tm)
            lines.append(
                f"IFC read, floor plate of {bars} bars: plain {_rate(tp, bars, pieces)}, mapped "
                f"{_rate(tm, bars, pieces)}, {tp / tm:.2f}x plain's rate"
            )
        path = write_shaft(Path(tmp) / "shaft.ifc", storeys=shaft_storeys)
        t, bars, pieces, layout = read(path)
    ratio = sizes[-1] / sizes[0]
    return [
        *lines,
        f"growth {sizes[0]} -> {sizes[-1]} bars ({ratio:.0f}x): the mapped read {times[-1] / times[0]:.1f}x the "
        f"time (t ~ n^{np.log(times[-1] / times[0]) / np.log(ratio):.2f})",
        f"IFC read, lift shaft of {bars} bars as mapped items ({6 * shaft_storeys} elements, "
        f"{len(layout.faces.fits)} faces): {_rate(t, bars, pieces)}, {t / 5.0:.2f}x the 5 s goal",
    ]


def _ifc_lines() -> list[str]:
    try:
        import ifcopenshell  # noqa: F401
    except ImportError:
        return ["IFC floor plate: skipped (IfcOpenShell, the ifc extra, is not installed)"]
    return ifc_bench() + read_bench()
