"""The plots the paper shows, and a little more: validation metrics against epochs, precision-recall
curves, and a grid of test images with predictions over ground truth."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from rebar_data.perception.evaluation.data import Sample, read_image  # noqa: E402
from rebar_data.perception.evaluation.metrics import RECALL_THRESHOLDS, APResult, PixelResult  # noqa: E402

TRUTH_RGB = (40, 220, 40)
OCCLUDED_RGB = (60, 140, 255)
PRED_RGB = (255, 40, 40)


def _col(history: Sequence[dict], key: str) -> np.ndarray:
    return np.array([float(h.get(key, np.nan)) for h in history])


def plot_history(history: Sequence[dict], path: str | Path, *, mosaic_epochs: int | None = None) -> Path:
    """Training loss and validation metrics against epochs (one row of ``history`` per epoch)."""
    ep = _col(history, "epoch")
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ax = axes[0]
    for key, label in (
        ("train_loss", "total"),
        ("train_heat_loss", "heatmap"),
        ("train_offset_loss", "offset"),
    ):
        ax.plot(ep, _col(history, key), label=label)
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
