"""Figures of a training run and of the model card: training curves, precision-recall curves and frames with
their detections drawn over the ground truth. The card's ship beside it, each at most ``MAX_FIGURE_BYTES``."""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from rebar_data.perception.evaluation.data import Sample, read_image  # noqa: E402
from rebar_data.perception.evaluation.metrics import RECALL_THRESHOLDS, APResult, PixelResult  # noqa: E402
from rebar_data.perception.inference.detector import OPERATING_THRESHOLD  # noqa: E402

TRUTH_RGB = (40, 220, 40)
OCCLUDED_RGB = (60, 140, 255)
PRED_RGB = (255, 40, 40)
MAX_FIGURE_BYTES = 100 * 1024
FRAME_COLOURS = 128  # a frame's PNG palette: sensor noise makes a true-colour PNG several times larger


def read_history(path: str | Path) -> list[dict[str, float]]:
    """The rows of a run's metrics.csv (one per first-stage epoch) as numbers; an empty cell is NaN."""
    with Path(path).open() as f:
        return [{k: float(v) if v else float("nan") for k, v in row.items()} for row in csv.DictReader(f)]


def _col(rows: Sequence[dict], key: str) -> np.ndarray:
    return np.array([float(r.get(key, np.nan)) for r in rows])


def _save(fig, path: str | Path, *, dpi: int = 100, limited: bool = True) -> Path:
    """Save a figure and close it; a ``limited`` one over ``MAX_FIGURE_BYTES`` is a bug in its layout."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    if limited and Path(path).stat().st_size > MAX_FIGURE_BYTES:
        raise RuntimeError(f"{path}: {Path(path).stat().st_size} bytes, over {MAX_FIGURE_BYTES}")
    return Path(path)


def plot_history(
    history: Sequence[dict],
    path: str | Path,
    *,
    stages: dict[str, Sequence[dict]] | None = None,
    adapt: Sequence[dict] = (),
    best_epoch: int | None = None,
    mosaic_epochs: int | None = None,
) -> Path:
    """Training curves: the first stage's losses per epoch (its adapt epochs after them), its validation
    figures, and each later stage's loss per epoch (``stages``: name -> rows with ``epoch`` and ``loss`` or
    ``loss_px``). ``best_epoch`` None: the epoch of the best validation AP."""
    fig, axes = plt.subplots(1, 3, figsize=(10.5, 3.2))
    ep = _col(history, "epoch")
    for key, label in (
        ("train_loss", "total"),
        ("train_heat_loss", "heatmap"),
        ("train_offset_loss", "offset"),
    ):
        axes[0].plot(ep, _col(history, key), label=label)
    if adapt:
        after = (ep.max() if len(ep) else 0) + _col(adapt, "epoch")
        axes[0].plot(after, _col(adapt, "train_loss"), "k.-", lw=1, label="adapt epochs (total)")
    for key, label in (
        ("val_oks_ap50", "AP@0.5"),
        ("val_pck2", "PCK@2px"),
        ("val_recall_at_p99", "recall@P0.99"),
    ):
        col = _col(history, key)
        axes[1].plot(ep[np.isfinite(col)], col[np.isfinite(col)], marker=".", label=label)
    axes[1].set_ylim(0, 1.01)
    for name, rows in (stages or {}).items():
        if rows:
            key = "loss" if "loss" in rows[0] else "loss_px"
            axes[2].plot(_col(rows, "epoch"), _col(rows, key), marker=".", label=f"{name} ({key})")
    ap = _col(history, "val_oks_ap")
    if best_epoch is None and np.isfinite(ap).any():
        best_epoch = int(ep[np.nanargmax(ap)])
    titles = (
        "first stage: training loss",
        "first stage: validation (val subset)",
        "later stages: training loss",
    )
    for ax, title in zip(axes, titles, strict=True):
        if ax is not axes[1]:
            ax.set_yscale("log")
        if ax is not axes[2] and best_epoch is not None:
            ax.axvline(best_epoch, color="grey", ls="--", lw=0.8, label=f"best epoch {best_epoch}")
        if ax is not axes[2] and mosaic_epochs and len(ep) and mosaic_epochs < ep.max():
            ax.axvline(mosaic_epochs + 0.5, color="grey", ls=":", lw=1, label="mosaic off")
        lo, hi = ax.get_xlim()
        if hi - lo < 2:  # one or two epochs: a span of whole epochs, so the ticks fall on them
            ax.set_xlim((lo + hi) / 2 - 1, (lo + hi) / 2 + 1)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("epoch", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    return _save(fig, path)


def plot_pr_modes(
    curves: dict[str, tuple[APResult, PixelResult]], path: str | Path, *, title: str, subtitle: str = ""
) -> Path:
    """Precision against recall at OKS 0.5 (COCO interpolation), a curve per input mode (name -> its AP and
    pixel results) with its operating point, and the precision 0.99 line. When every curve keeps precision 0.9
    up to recall 0.8 the axes show that corner alone, where the modes differ."""
    fig, ax = plt.subplots(figsize=(4.6, 3.6))
    corner = all((ap.precision[0][RECALL_THRESHOLDS <= 0.8] >= 0.9).all() for ap, _ in curves.values())
    for k, (mode, (ap, px)) in enumerate(curves.items()):
        label = f"{mode}: AP@0.5 {ap.ap50:.3f}, R@P0.99 {px.recall_at_p99:.3f}"
        ax.plot(RECALL_THRESHOLDS, ap.precision[0], color=f"C{k}", label=label)
        if px.n_gt:
            ax.plot([px.recall], [px.precision], "o", color=f"C{k}", ms=4)
    ax.axhline(0.99, color="grey", ls=":", lw=0.8)
    ax.set_xlabel("recall", fontsize=8)
    ax.set_ylabel("precision", fontsize=8)
    ax.set_xlim(*((0.8, 1.002) if corner else (0, 1.01)))
    ax.set_ylim(*((0.9, 1.002) if corner else (0, 1.01)))
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    ax.set_title(title + (f"\n{subtitle}" if subtitle else ""), fontsize=8)
    ax.legend(loc="lower left", fontsize=7, title=f"dots: score {OPERATING_THRESHOLD:g}", title_fontsize=7)
    return _save(fig, path)


def draw_overlay(
    rgb: np.ndarray,
    predictions: np.ndarray,
    *,
    truth: np.ndarray | None = None,
    occluded: np.ndarray | None = None,
    threshold: float = 0.5,
    scale: int = 2,
) -> np.ndarray:
    """The image enlarged ``scale`` times with ground truth (green circles, occluded in blue) and
    predictions of score >= ``threshold`` (red crosses)."""
    img = cv2.resize(rgb, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)

    def pt(u: float, v: float) -> tuple[int, int]:  # COCO corner origin to OpenCV's 1/16 px pixel centres
        return int(round((u * scale - 0.5) * 16)), int(round((v * scale - 0.5) * 16))

    for pts, colour in ((truth, TRUTH_RGB), (occluded, OCCLUDED_RGB)):
        for u, v in np.asarray(pts if pts is not None else np.zeros((0, 2))).reshape(-1, 2):
            cv2.circle(img, pt(u, v), 6 * scale * 16, colour, 1, cv2.LINE_AA, 4)
    r = 3 * scale * 16
    for u, v, s in np.asarray(predictions).reshape(-1, 3):
        if s >= threshold:
            c = pt(u, v)
            cv2.line(img, (c[0] - r, c[1]), (c[0] + r, c[1]), PRED_RGB, 1, cv2.LINE_AA, 4)
            cv2.line(img, (c[0], c[1] - r), (c[0], c[1] + r), PRED_RGB, 1, cv2.LINE_AA, 4)
    return img


def plot_prediction_grid(
    samples: Sequence[Sample], predictions: Sequence[np.ndarray], path: str | Path, *, max_images: int = 6
) -> Path:
    """Up to ``max_images`` images, spread over the samples, with predictions over ground truth."""
    n = min(len(samples), max_images)
    rows = max(1, -(-n // 3))
    fig, axes = plt.subplots(rows, 3, figsize=(18, 4.8 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, k in zip(axes.ravel(), np.linspace(0, len(samples) - 1, n).round().astype(int), strict=False):
        s, p = samples[k], np.asarray(predictions[k]).reshape(-1, 3)
        ax.imshow(draw_overlay(read_image(s.path), p, truth=s.visible, occluded=s.occluded, scale=1))
        found = int((p[:, 2] >= OPERATING_THRESHOLD).sum())
        ax.set_title(f"{s.image_id}: {len(s.visible)} visible crossings, {found} found", fontsize=9)
    fig.suptitle("green: ground truth (blue: occluded), red: predictions", fontsize=10)
    return _save(fig, path, dpi=90, limited=False)  # a run's own figure, not shipped


def write_frame(
    rgb: np.ndarray,
    predictions: np.ndarray,
    path: str | Path,
    *,
    truth: np.ndarray | None = None,
    occluded: np.ndarray | None = None,
) -> tuple[Path, float]:
    """One frame with its detections drawn (:func:`draw_overlay`) as a PNG of ``FRAME_COLOURS`` colours: at
    full size when it fits in ``MAX_FIGURE_BYTES``, else shrunk by steps of 0.85 until it does; returns the
    file written and the scale it was drawn at."""
    from PIL import Image

    preds = np.asarray(predictions, float).reshape(-1, 3)
    h, w = rgb.shape[:2]
    scale = 1.0
    while True:
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        small = rgb if scale == 1.0 else cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        to_small = np.array([size[0] / w, size[1] / h])
        truth_s, occluded_s = (
            None if uv is None else np.asarray(uv, float).reshape(-1, 2) * to_small
            for uv in (truth, occluded)
        )
        img = draw_overlay(
            small,
            np.c_[preds[:, :2] * to_small, preds[:, 2]],
            truth=truth_s,
            occluded=occluded_s,
            threshold=OPERATING_THRESHOLD,
            scale=1,
        )
        out = io.BytesIO()
        palette = Image.fromarray(img).quantize(
            FRAME_COLOURS, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE
        )
        palette.save(out, "PNG", optimize=True)
        if out.tell() <= MAX_FIGURE_BYTES or min(size) <= 32:
            break
        scale *= 0.85
    if out.tell() > MAX_FIGURE_BYTES:
        raise RuntimeError(f"{path}: {out.tell()} bytes at {size[0]}x{size[1]} px, over {MAX_FIGURE_BYTES}")
    Path(path).write_bytes(out.getvalue())
    return Path(path), scale
