"""Pictures for the audit: distributions of the labels and randomized parameters, and a contact sheet."""

from __future__ import annotations

from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from rebar_data.dataset import layout  # noqa: E402

COVERAGE_GROUPS = {
    "light_": "lighting",
    "mat_": "rebar material",
    "surr_": "surroundings",
    "sensor_": "sensor",
}
COVERAGE_BINS = 24
NOT_PLOTTED_SUFFIXES = ("_seed",)  # random seeds vary by design; their spread says nothing about coverage
ROW_IN = 0.27  # height of a parameter's row (inches at 100 dpi)
COLUMN_IN = 7.0  # width of a column of rows
STRIP = (0.47, 0.87)  # the part of a row the distribution takes (fraction of the column)
LISTING_CHARS = 58  # characters a line of a categorical parameter's counts holds


def write_png(path: Path, rgb: np.ndarray) -> None:
    """An RGB image as a PNG file, encoded in memory and written by Python: a failed write (a full disk)
    raises, where ``cv2.imwrite`` returns False and libpng prints to stderr."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError(f"PNG encoding failed for {path}")
    Path(path).write_bytes(buf.tobytes())


def split_parameters(S: pd.DataFrame) -> tuple[list[str], dict[str, object]]:
    """The randomized columns of the samples table (``layout.RANDOMIZED_PREFIXES``): those that vary over the
    images, and the constant ones with their value (JSON types)."""
    varying, constant = [], {}
    for c in layout.randomized_columns(S.columns):
        values = S[c].drop_duplicates()
        if len(values) > 1:
            varying.append(c)
        elif len(values) == 1:
            v = values.iloc[0]
            constant[c] = v.item() if isinstance(v, np.generic) else v
    return varying, constant


def distribution_plots(S: pd.DataFrame, K: pd.DataFrame, out: Path) -> dict:
    """Keypoints per image, visibility per split, and the coverage of the randomized parameters that vary."""
    per_image = K[K.visibility == 2].groupby("image_id").size().reindex(S.image_id, fill_value=0)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.hist(per_image.to_numpy(), bins=30, color="#b5651d")
    ax.set_xlabel("visible keypoints per image")
    ax.set_ylabel("images")
    fig.tight_layout()
    fig.savefig(out / "keypoints_per_image.png", dpi=100)
    plt.close(fig)

    vis = K.groupby(["split", "visibility"]).size().unstack(fill_value=0)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    vis.reindex([s for s in layout.SPLITS if s in vis.index]).plot.bar(ax=ax, stacked=False, rot=0)
    ax.set_ylabel("keypoints")
    ax.set_yscale("log")
    ax.legend(["0 outside", "1 occluded", "2 visible"][: len(vis.columns)])
    fig.tight_layout()
    fig.savefig(out / "visibility.png", dpi=100)
    plt.close(fig)

    varying, constant = split_parameters(S)
    coverage_plot(S, [c for c in varying if not c.endswith(NOT_PLOTTED_SUFFIXES)], out / "coverage.png")

    counts = K.visibility.value_counts().to_dict()
    return {
        "images": int(len(S)),
        "visible_per_image_mean": round(float(per_image.mean()), 2) if len(per_image) else 0.0,
        "visible_per_image_min": int(per_image.min()) if len(per_image) else 0,
        "visible_per_image_max": int(per_image.max()) if len(per_image) else 0,
        "visibility_counts": {int(k): int(v) for k, v in sorted(counts.items())},
        "images_per_split": {s: int((S.split == s).sum()) for s in layout.SPLITS},
        "randomized_columns": len(varying) + len(constant),
        "varying_parameters": len(varying),
    }


def coverage_plot(S: pd.DataFrame, columns: list[str], path: Path) -> None:
    """One row per parameter, grouped by kind in two columns: a numeric parameter's histogram over the
    images between its smallest and largest value (printed at the ends), a categorical one's count of
    images per value. Constant parameters are not drawn (the audit report lists them)."""
    rows = {c: _listing(S[c]) for c in columns}
    size = {c: 1.0 if rows[c] is None else 0.2 + 0.8 * len(rows[c]) for c in columns}
    groups = [
        (title, [c for c in columns if c.startswith(prefix)]) for prefix, title in COVERAGE_GROUPS.items()
    ]
    groups = [(t, cs) for t, cs in groups if cs]
    heights = [1.5 + sum(size[c] for c in cs) for _, cs in groups]
    # two columns of about equal height, groups kept whole
    best = min(range(1, len(groups) + 1), key=lambda k: abs(sum(heights[:k]) - sum(heights[k:])), default=0)
    sides = [s for s in (groups[:best], groups[best:]) if s] or [[]]
    height = max(sum(1.5 + sum(size[c] for c in cs) for _, cs in side) for side in sides)
    fig_h = ROW_IN * max(height, 2) + 0.7
    fig = plt.figure(figsize=(COLUMN_IN * len(sides), fig_h))
    fig.text(
        0.5,
        1 - 0.25 / fig_h,
        f"Randomized parameters that vary over the {len(S)} images (constant ones: audit/report.md)",
        fontsize=11,
        ha="center",
        va="center",
    )
    for i, side in enumerate(sides):
        ax = fig.add_axes((i / len(sides) + 0.01, 0.1 / fig_h, 1 / len(sides) - 0.02, 1 - 0.6 / fig_h))
        y = 0.0
        for title, cols in side:
            ax.text(0.0, y + 0.3, title, fontsize=10.5, fontweight="bold", va="center")
            y += 1.2
            for c in cols:
                _coverage_row(ax, S[c], c, y, rows[c])
                y += size[c]
            y += 0.3
        ax.set_xlim(0, 1)
        ax.set_ylim(max(height, 2) - 0.2, -0.4)
        ax.axis("off")
        if not side:
            ax.text(0.5, 0.5, "no randomized parameter varies", ha="center", fontsize=11)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _listing(col: pd.Series) -> list[str] | None:
    """A categorical parameter's ``value: images`` pairs as lines of at most ``LISTING_CHARS`` (None for a
    numeric parameter)."""
    if not (pd.api.types.is_bool_dtype(col) or not pd.api.types.is_numeric_dtype(col)):
        return None
    counts = col.astype(str).value_counts().sort_index()
    lines = [""]
    for value, n in counts.items():
        item = f"{value or '(empty)'}: {n}"
        if lines[-1] and len(lines[-1]) + 3 + len(item) > LISTING_CHARS:
            lines.append("")
        lines[-1] += ("   " if lines[-1] else "") + item
    return lines


def _coverage_row(ax, col: pd.Series, name: str, y: float, listing: list[str] | None) -> None:
    ax.text(0.0, y, name, fontsize=9, va="center", family="monospace")
    lo, hi = STRIP
    if listing is not None:
        for k, line in enumerate(listing):
            ax.text(lo, y + 0.8 * k, line, fontsize=8.5, va="center", color="#1f3864")
        return
    v = col.to_numpy(float)
    v = v[np.isfinite(v)]
    if not len(v):
        ax.text(lo, y, "no finite value", fontsize=8.5, va="center", color="#c00000")
        return
    vmin, vmax = float(v.min()), float(v.max())
    counts, _ = np.histogram(v, bins=COVERAGE_BINS, range=(vmin, vmax))
    width = (hi - lo) / COVERAGE_BINS
    centres = lo + width * (np.arange(COVERAGE_BINS) + 0.5)
    heights = 0.72 * counts / max(counts.max(), 1)
    ax.plot([lo, hi], [y + 0.38, y + 0.38], color="#bbbbbb", lw=0.8)
    ax.bar(centres, heights, width=width * 0.9, bottom=y + 0.38 - heights, color="#4472c4")
    ax.text(lo - 0.008, y, _number(vmin), fontsize=8, va="center", ha="right")
    ax.text(hi + 0.008, y, _number(vmax), fontsize=8, va="center", ha="left")


def _number(x: float) -> str:
    return f"{x:.0f}" if 1e4 <= abs(x) < 1e10 else f"{x:.4g}"


def draw_keypoints(img: np.ndarray, g: pd.DataFrame) -> np.ndarray:
    """Visible keypoints as green crosses in their box, occluded ones as orange circles."""
    out = img.copy()
    for kp in g[g.visibility > 0].itertuples():
        p = (int(round(kp.u * 4)), int(round(kp.v * 4)))  # 2 fractional bits for sub-pixel drawing
        if kp.visibility == 2:
            h = kp.box_size_px / 2
            tl = (int(round((kp.u - h) * 4)), int(round((kp.v - h) * 4)))
            br = (int(round((kp.u + h) * 4)), int(round((kp.v + h) * 4)))
            cv2.rectangle(out, tl, br, (60, 220, 60), 1, cv2.LINE_AA, shift=2)
            cv2.drawMarker(out, (p[0] // 4, p[1] // 4), (60, 255, 60), cv2.MARKER_CROSS, 8, 1, cv2.LINE_AA)
        elif kp.visibility == 1:
            cv2.circle(out, p, 4 * 4, (255, 150, 0), 1, cv2.LINE_AA, shift=2)
    return out


def contact_sheet(
    ds: Path, S: pd.DataFrame, K: pd.DataFrame, path: Path, *, n: int = 24, tile: int = 320
) -> None:
    """A grid of images spread over splits and trajectories, keypoints drawn, each titled with its id."""
    pick = S.sort_values(["split", "trajectory_id", "frame"]).iloc[
        np.linspace(0, len(S) - 1, min(n, len(S))).astype(int)
    ]
    cols = 6
    rows = int(np.ceil(len(pick) / cols))
    first = pick.iloc[0]
    tile_h = int(round(tile * first.height / max(first.width, first.height)))
    sheet = np.full((rows * (tile_h + 18), cols * tile, 3), 30, np.uint8)
    for i, row in enumerate(pick.itertuples()):
        img = cv2.cvtColor(cv2.imread(str(ds / row.file_name)), cv2.COLOR_BGR2RGB)
        img = draw_keypoints(img, K[K.image_id == row.image_id])
        scale = tile / max(img.shape[:2])
        img = cv2.resize(
            img, (int(img.shape[1] * scale), int(img.shape[0] * scale)), interpolation=cv2.INTER_AREA
        )
        r, c = divmod(i, cols)
        y, x = r * (tile_h + 18), c * tile
        sheet[y + 18 : y + 18 + img.shape[0], x : x + img.shape[1]] = img
        label = f"{row.split} {row.image_id} ({row.n_visible} vis)"
        cv2.putText(
            sheet,
            label[:44],
            (x + 3, y + 13),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.36,
            (230, 230, 230),
            1,
            cv2.LINE_AA,
        )
    write_png(path, sheet)


def _read_depth_m(ds: Path, rel: object) -> np.ndarray | None:
    if not isinstance(rel, str):
        return None
    d = cv2.imread(str(ds / rel), cv2.IMREAD_UNCHANGED)
    return None if d is None else d.astype(np.float32) / 1000.0


def sensor_depth_stats(ds: Path, S: pd.DataFrame, *, per_model: int = 100) -> dict:
    """Per depth sensor model, over up to ``per_model`` of its images: how many images, the share of the
    pixels with a surface (exact depth > 0) that the sensor measured (mean and range), and the median
    absolute difference from the exact depth where both have a value (mm)."""
    if "sensor_depth_file" not in S.columns or "sensor_depth_model" not in S.columns:
        return {}
    rows = S[S.sensor_depth_file.notna() & S.depth_file.notna()]
    out = {}
    for model, g in rows.groupby("sensor_depth_model"):
        pick = g.iloc[np.linspace(0, len(g) - 1, min(per_model, len(g))).astype(int)]
        shares, diffs = [], []
        for row in pick.itertuples():
            exact, sensed = _read_depth_m(ds, row.depth_file), _read_depth_m(ds, row.sensor_depth_file)
            if exact is None or sensed is None:
                continue
            surface = exact > 0
            shares.append(float((sensed[surface] > 0).mean()) if surface.any() else 0.0)
            both = surface & (sensed > 0)
            if both.any():
                diffs.append(np.abs(sensed[both] - exact[both]) * 1000.0)
        out[str(model)] = {
            "images": int(len(g)),
            "valid_fraction_mean": round(float(np.mean(shares)), 4) if shares else 0.0,
            "valid_fraction_min": round(float(np.min(shares)), 4) if shares else 0.0,
            "valid_fraction_max": round(float(np.max(shares)), 4) if shares else 0.0,
            "abs_error_median_mm": round(float(np.median(np.concatenate(diffs))), 2) if diffs else None,
        }
    return out


def _depth_colour(depth_m: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Depth as a colour map (near yellow, far purple), no measurement black."""
    x = np.clip((depth_m - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    img = cv2.applyColorMap(np.round(255 * (1.0 - x)).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    img[depth_m <= 0] = 0
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def sensor_depth_sheet(ds: Path, S: pd.DataFrame, path: Path, *, tile: int = 320) -> bool:
    """One row per depth sensor model in the dataset: a colour frame, its exact depth and the sensor's depth
    (one colour scale a row, black = no measurement). False (nothing written) without sensor depth maps."""
    if "sensor_depth_file" not in S.columns or "sensor_depth_model" not in S.columns:
        return False
    rows = S[S.sensor_depth_file.notna() & S.depth_file.notna()].sort_values("image_id")
    picks = [g.iloc[len(g) // 2] for _, g in rows.groupby("sensor_depth_model")]
    picks = [r for r in picks if _read_depth_m(ds, r.depth_file) is not None]
    picks = [r for r in picks if _read_depth_m(ds, r.sensor_depth_file) is not None]
    if not picks:
        return False
    first = picks[0]
    tile_h = int(round(tile * first.height / max(first.width, first.height)))
    sheet = np.full((len(picks) * (tile_h + 18), 3 * tile, 3), 30, np.uint8)
    for r, row in enumerate(picks):
        rgb = cv2.cvtColor(cv2.imread(str(ds / row.file_name)), cv2.COLOR_BGR2RGB)
        exact, sensed = _read_depth_m(ds, row.depth_file), _read_depth_m(ds, row.sensor_depth_file)
        surface = exact[exact > 0]
        lo, hi = np.percentile(surface, [1, 99]) if surface.size else (0.0, 1.0)
        panels = [rgb, _depth_colour(exact, lo, hi), _depth_colour(sensed, lo, hi)]
        share = float((sensed[exact > 0] > 0).mean()) if surface.size else 0.0
        titles = [
            f"{row.image_id}",
            f"exact depth {lo:.2f}-{hi:.2f} m",
            f"{row.sensor_depth_model}: {share:.0%} measured",
        ]
        y = r * (tile_h + 18)
        for c, (img, title) in enumerate(zip(panels, titles, strict=True)):
            scale = tile / max(img.shape[:2])
            size = (int(img.shape[1] * scale), int(img.shape[0] * scale))
            img = cv2.resize(img, size, interpolation=cv2.INTER_NEAREST if c else cv2.INTER_AREA)
            sheet[y + 18 : y + 18 + img.shape[0], c * tile : c * tile + img.shape[1]] = img
            cv2.putText(
                sheet,
                title[:44],
                (c * tile + 3, y + 13),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.36,
                (230, 230, 230),
                1,
                cv2.LINE_AA,
            )
    write_png(path, sheet)
    return True
