"""The plots the paper shows, and a little more: validation metrics against epochs, precision-recall
curves, and a grid of test images with predictions over ground truth."""

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


def _col(history: Sequence[dict], key: str) -> np.ndarray:
    return np.array([float(h.get(key, np.nan)) for h in history])


def _plot_first_stage_losses(ax, history: Sequence[dict], ep: np.ndarray) -> None:
    """The first stage's training losses (total, heatmap, offset) per epoch on ``ax``."""
    for key, label in (
        ("train_loss", "total"),
        ("train_heat_loss", "heatmap"),
        ("train_offset_loss", "offset"),
    ):
        ax.plot(ep, _col(history, key), label=label)


def plot_history(history: Sequence[dict], path: str | Path, *, mosaic_epochs: int | None = None) -> Path:
    """Training loss and validation metrics against epochs (one row of ``history`` per epoch)."""
    ep = _col(history, "epoch")
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ax = axes[0]
    _plot_first_stage_losses(ax, history, ep)
    ax.set_yscale("log")
    ax.set_title("training loss")
    ax = axes[1]
    for key, label in (
        ("val_oks_ap50", "OKS AP@0.5"),
        ("val_oks_ap", "OKS AP@0.5:0.95"),
        ("val_recall_at_p99", "recall@P0.99"),
    ):
        ax.plot(ep, _col(history, key), marker=".", label=label)
    ax.set_ylim(0, 1.01)
    ax.set_title("validation: detection")
    ax = axes[2]
    for key, label in (("val_pck1", "PCK@1px"), ("val_pck2", "PCK@2px"), ("val_pck5", "PCK@5px")):
        ax.plot(ep, _col(history, key), marker=".", label=label)
    ax.set_ylim(0, 1.01)
    ax.set_title("validation: localisation")
    best = (
        np.nanargmax(_col(history, "val_oks_ap")) if np.isfinite(_col(history, "val_oks_ap")).any() else None
    )
    for ax in axes:
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
        if mosaic_epochs and mosaic_epochs < (ep.max() if len(ep) else 0):
            ax.axvline(mosaic_epochs + 0.5, color="grey", ls=":", lw=1, label="mosaic off")
        if best is not None:
            ax.axvline(ep[best], color="k", ls="--", lw=0.8, label=f"best (epoch {int(ep[best])})")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def plot_pr(ap: APResult, px: PixelResult, path: str | Path, *, title: str = "") -> Path:
    """Precision against recall: at OKS 0.5 and 0.75 (COCO interpolation) and with the 5 px gate."""
    fig, ax = plt.subplots(figsize=(6, 5))
    for ti, t in ((0, 0.5), (5, 0.75)):
        if ti < len(ap.precision):
            ax.plot(RECALL_THRESHOLDS, ap.precision[ti], label=f"OKS {t} (AP {ap.precision[ti].mean():.3f})")
    ax.plot(px.curve_recall, px.curve_precision, lw=1, ls="--", label="5 px gate, raw")
    if px.n_gt:
        ax.plot(
            [px.recall],
            [px.precision],
            "ko",
            label=f"score {px.threshold:g}: P {px.precision:.3f}, R {px.recall:.3f}",
        )
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1.01)
    ax.set_ylim(0, 1.01)
    ax.grid(alpha=0.3)
    ax.set_title(title or f"precision-recall (OKS sigma {ap.sigma:g}); AP@0.5:0.95 {ap.ap:.3f}")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


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
    predictions of score >= ``threshold`` (red crosses, the score beside each)."""
    img = cv2.resize(rgb, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    shift = 4  # OpenCV's fixed-point bits: 16 steps a pixel

    def pt(u: float, v: float) -> tuple[int, int]:
        # COCO corner origin to OpenCV's pixel-centre indices, in the enlarged image
        return int(round((u * scale - 0.5) * 16)), int(round((v * scale - 0.5) * 16))

    for pts, colour in ((truth, TRUTH_RGB), (occluded, OCCLUDED_RGB)):
        for u, v in np.asarray(pts if pts is not None else np.zeros((0, 2))).reshape(-1, 2):
            cv2.circle(img, pt(u, v), 6 * scale * 16, colour, 1, cv2.LINE_AA, shift)
    for u, v, s in np.asarray(predictions).reshape(-1, 3):
        if s < threshold:
            continue
        c = pt(u, v)
        r = 3 * scale * 16
        cv2.line(img, (c[0] - r, c[1]), (c[0] + r, c[1]), PRED_RGB, 1, cv2.LINE_AA, shift)
        cv2.line(img, (c[0], c[1] - r), (c[0], c[1] + r), PRED_RGB, 1, cv2.LINE_AA, shift)
    return img


def plot_prediction_grid(
    samples: Sequence[Sample],
    predictions: Sequence[np.ndarray],
    path: str | Path,
    *,
    threshold: float = 0.5,
    columns: int = 3,
    max_images: int = 6,
) -> Path:
    """A grid of images with predictions over ground truth, and a zoomed crop of each image's centre."""
    n = min(len(samples), max_images)
    idx = np.linspace(0, len(samples) - 1, n).round().astype(int) if n else []
    rows = max(1, -(-n // columns))
    fig, axes = plt.subplots(rows, columns, figsize=(6 * columns, 4.8 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, k in zip(axes.ravel(), idx, strict=False):
        s, p = samples[k], predictions[k]
        img = draw_overlay(
            read_image(s.path), p, truth=s.visible, occluded=s.occluded, threshold=threshold, scale=1
        )
        ax.imshow(img)
        n_hit = int((np.asarray(p).reshape(-1, 3)[:, 2] >= threshold).sum())
        ax.set_title(f"{s.image_id}: {len(s.visible)} visible crossings, {n_hit} found", fontsize=9)
    fig.suptitle("green: ground truth (blue: occluded), red: predictions", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return Path(path)


# The model card's figures: small PNGs that ship beside it (``models/card/``).
MAX_FIGURE_BYTES = 100 * 1024
CARD_DPI = 100


def read_history(path: str | Path) -> list[dict[str, float]]:
    """The rows of a run's metrics.csv (one per first-stage epoch) as numbers; an empty cell is NaN."""
    with Path(path).open() as f:
        return [
            {k: float(v) if v not in ("", None) else float("nan") for k, v in row.items()}
            for row in csv.DictReader(f)
        ]


def _save_small(fig, path: str | Path) -> Path:
    """Save a card figure and close it; a figure over ``MAX_FIGURE_BYTES`` is a bug in its layout."""
    path = Path(path)
    fig.savefig(path, dpi=CARD_DPI)
    plt.close(fig)
    if path.stat().st_size > MAX_FIGURE_BYTES:
        raise RuntimeError(f"{path}: {path.stat().st_size} bytes, over the card's {MAX_FIGURE_BYTES}")
    return path


def plot_training(
    history: Sequence[dict],
    path: str | Path,
    *,
    stages: dict[str, Sequence[dict]] | None = None,
    adapt: Sequence[dict] = (),
    best_epoch: int | None = None,
) -> Path:
    """The card's training curves: the first stage's loss per epoch (its adapt epochs after it), its
    validation figures per epoch, and each later stage's loss per epoch (``stages``: name -> its rows, each
    with ``epoch`` and ``loss`` or ``loss_px``)."""
    fig, axes = plt.subplots(1, 3, figsize=(10.5, 3.2))
    ep = _col(history, "epoch")
    ax = axes[0]
    _plot_first_stage_losses(ax, history, ep)
    if adapt:
        last = ep.max() if len(ep) else 0
        ax.plot(
            last + _col(adapt, "epoch"), _col(adapt, "train_loss"), "k.-", lw=1, label="adapt epochs (total)"
        )
    ax.set_yscale("log")
    ax.set_title("first stage: training loss", fontsize=9)
    ax = axes[1]
    for key, label in (
        ("val_oks_ap50", "AP@0.5"),
        ("val_pck2", "PCK@2px"),
        ("val_recall_at_p99", "recall@P0.99"),
    ):
        col = _col(history, key)
        ok = np.isfinite(col)
        ax.plot(ep[ok], col[ok], marker=".", label=label)
    ax.set_ylim(0, 1.01)
    ax.set_title("first stage: validation (val subset)", fontsize=9)
    if best_epoch is not None:
        for ax in axes[:2]:
            ax.axvline(best_epoch, color="grey", ls="--", lw=0.8, label=f"best epoch {best_epoch}")
    ax = axes[2]
    for name, rows in (stages or {}).items():
        if not rows:
            continue
        key = "loss" if "loss" in rows[0] else "loss_px"
        ax.plot(_col(rows, "epoch"), _col(rows, key), marker=".", label=f"{name} ({key})")
    ax.set_yscale("log")
    ax.set_title("later stages: training loss", fontsize=9)
    for ax in axes:
        lo, hi = ax.get_xlim()
        if hi - lo < 2:  # one or two epochs: a span of whole epochs, so the ticks fall on them
            ax.set_xlim((lo + hi) / 2 - 1, (lo + hi) / 2 + 1)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlabel("epoch", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    return _save_small(fig, path)


def plot_pr_modes(
    curves: dict[str, tuple[APResult, PixelResult]], path: str | Path, *, title: str, subtitle: str = ""
) -> Path:
    """One held-out set's precision-recall curves at OKS 0.5 (COCO interpolation), one per input mode
    (name -> its AP and pixel results), each with its operating point and the precision 0.99 line. When every
    curve keeps precision 0.9 up to recall 0.8 the axes show that corner alone (recall 0.8-1, precision
    0.9-1), where the modes differ."""
    fig, ax = plt.subplots(figsize=(4.6, 3.6))
    corner = all((ap.precision[0][RECALL_THRESHOLDS <= 0.8] >= 0.9).all() for ap, _ in curves.values())
    for k, (mode, (ap, px)) in enumerate(curves.items()):
        colour = f"C{k}"
        ax.plot(
            RECALL_THRESHOLDS,
            ap.precision[0],
            color=colour,
            label=f"{mode}: AP@0.5 {ap.ap50:.3f}, R@P0.99 {px.recall_at_p99:.3f}",
        )
        if px.n_gt:
            ax.plot([px.recall], [px.precision], "o", color=colour, ms=4)
    ax.axhline(0.99, color="grey", ls=":", lw=0.8)
    ax.set_xlabel("recall", fontsize=8)
    ax.set_ylabel("precision", fontsize=8)
    ax.set_xlim(*((0.8, 1.002) if corner else (0, 1.01)))
    ax.set_ylim(*((0.9, 1.002) if corner else (0, 1.01)))
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    ax.set_title(title + (f"\n{subtitle}" if subtitle else ""), fontsize=8)
    ax.legend(loc="lower left", fontsize=7, title=f"dots: score {OPERATING_THRESHOLD:g}", title_fontsize=7)
    fig.tight_layout()
    return _save_small(fig, path)


def _png_bytes(rgb: np.ndarray, colours: int) -> bytes:
    """``rgb`` as a PNG of at most ``colours`` colours (an adaptive palette, no dithering): rendered frames
    carry sensor noise, which makes a true-colour PNG several times larger for no visible gain."""
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(rgb).quantize(colours, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE).save(
        out, "PNG", optimize=True
    )
    return out.getvalue()


def write_frame(
    rgb: np.ndarray,
    predictions: np.ndarray,
    path: str | Path,
    *,
    truth: np.ndarray | None = None,
    occluded: np.ndarray | None = None,
    threshold: float = OPERATING_THRESHOLD,
    max_bytes: int = MAX_FIGURE_BYTES,
    colours: int = 128,
) -> tuple[Path, float]:
    """One frame with its detections drawn (:func:`draw_overlay`), as a PNG of ``colours`` colours and at most
    ``max_bytes``: at full size when it fits, else shrunk by steps of 0.85 until it does.

    Returns:
        The file written and the scale it was drawn at.
    """
    path = Path(path)
    preds = np.asarray(predictions, float).reshape(-1, 3)
    h, w = rgb.shape[:2]
    scale = 1.0
    while True:
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        small = rgb if scale == 1.0 else cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        to_small = np.array([size[0] / w, size[1] / h])

        def at(uv: np.ndarray | None, to_small: np.ndarray = to_small) -> np.ndarray | None:
            return None if uv is None else np.asarray(uv, float).reshape(-1, 2) * to_small

        img = draw_overlay(
            small,
            np.c_[at(preds[:, :2]), preds[:, 2]],
            truth=at(truth),
            occluded=at(occluded),
            threshold=threshold,
            scale=1,
        )
        data = _png_bytes(img, colours)
        if len(data) <= max_bytes or min(size) <= 32:
            break
        scale *= 0.85
    if len(data) > max_bytes:
        raise RuntimeError(f"{path}: {len(data)} bytes at {size[0]}x{size[1]} px, over {max_bytes}")
    path.write_bytes(data)
    return path, scale
