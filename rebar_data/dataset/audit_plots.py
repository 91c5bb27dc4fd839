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

COVERAGE_PREFIXES = ("light_", "mat_", "surr_", "sensor_")


def distribution_plots(S: pd.DataFrame, K: pd.DataFrame, out: Path) -> dict:
    """Keypoints per image, visibility per split, and coverage of lighting/material/surroundings/sensor."""
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

    cols = [c for c in S.columns if c.startswith(COVERAGE_PREFIXES)]
    n = max(len(cols), 1)
    ncol = 4
    nrow = int(np.ceil(n / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4 * ncol, 2.4 * nrow), squeeze=False)
    for ax, c in zip(axes.flat, cols, strict=False):
        col = S[c]
        if pd.api.types.is_bool_dtype(col) or not pd.api.types.is_numeric_dtype(col):
            col.astype(str).value_counts().sort_index().plot.bar(ax=ax, rot=30, color="#4472c4")
        else:
            ax.hist(col.to_numpy(float), bins=20, color="#4472c4")
        ax.set_title(c, fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(cols) :]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out / "coverage.png", dpi=80)
    plt.close(fig)

    counts = K.visibility.value_counts().to_dict()
    return {
        "images": int(len(S)),
        "visible_per_image_mean": round(float(per_image.mean()), 2) if len(per_image) else 0.0,
        "visible_per_image_min": int(per_image.min()) if len(per_image) else 0,
        "visible_per_image_max": int(per_image.max()) if len(per_image) else 0,
        "visibility_counts": {int(k): int(v) for k, v in sorted(counts.items())},
        "images_per_split": {s: int((S.split == s).sum()) for s in layout.SPLITS},
        "randomized_columns": len(cols),
    }


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
    cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
