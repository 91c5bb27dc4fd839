"""Run a detector over a dataset's images and score it, for validation, `rebar score` and the model card."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from tqdm import tqdm

from rebar_data.perception.evaluation.data import SPLITS, Sample, load_split, read_image, sample_depth
from rebar_data.perception.evaluation.metrics import Truth, pixel_metrics, summary
from rebar_data.perception.inference.detector import Detector

LOW_THRESHOLD = 0.05  # predictions kept for scoring: enough of the tail for AP and precision-recall curves
RANDOM_SPLIT_FRACTION = 0.2  # the paper's frame-level 80:20 split
CALIBRATION_FLOOR = 0.01  # lowest raw score looked at when choosing the operating point
MAX_SCORE_BIAS = 4.0
BORDER_BAND_PX = 8.0  # the breakdown's band along the image border
LOWER_MAT_COLUMN = "surr_lower_layer"  # samples table: a second mat lies beneath the labelled bars


def truth_of(sample: Sample, *, ignore_occluded: bool = False) -> Truth:
    """A sample's ground truth for the metrics; occluded crossings become ignore regions if asked."""
    if ignore_occluded:
        return Truth(sample.visible, sample.box_size_px, sample.occluded, sample.occluded_box_size_px)
    return Truth(sample.visible, sample.box_size_px)


def predict(
    detector: Detector,
    samples: Sequence[Sample],
    *,
    threshold: float = LOW_THRESHOLD,
    images: Sequence[np.ndarray] | None = None,
    depth: bool = True,
    depth_from: str = "sensor",
    progress: bool = False,
    point: str = "sight",
) -> list[np.ndarray]:
    """Detections (N, 3) for each sample's image, read from disk unless ``images`` are given; with ``depth``
    each sample's depth image too (``depth_from``: :data:`~rebar_data.perception.evaluation.data.DEPTH_SOURCES`),
    when it has one and the detector has a depth check; ``point`` as :meth:`Detector.detect` takes it."""
    out = []
    use_depth = depth and detector.depth_check is not None
    for k, s in enumerate(tqdm(samples, desc="detect", unit="img", disable=not progress, leave=False)):
        rgb = images[k] if images is not None else read_image(s.path)
        d = sample_depth(s, depth_from) if use_depth else None
        out.append(detector.detect(rgb, threshold=threshold, camera=s.camera, depth=d, point=point))
    return out


def at_crossing_points(
    detector: Detector, samples: Sequence[Sample], predictions: Sequence[np.ndarray]
) -> list[np.ndarray]:
    """``predictions`` of the sight points with each u, v moved to where the crossing-point stage puts its 3D
    crossing point: ``predict(..., point="crossing")`` without running the other stages again."""
    out = []
    for s, p in zip(samples, predictions, strict=True):
        moved = np.array(p, dtype=np.float64, copy=True).reshape(-1, 3)
        if len(moved):
            camera = s.intrinsics or detector.default_camera(s.height, s.width)
            moved[:, :2] = detector.crossing_point.points(read_image(s.path), moved[:, :2], camera)
        out.append(moved)
    return out


def score(
    samples: Sequence[Sample],
    predictions: Sequence[np.ndarray],
    *,
    sigma: float,
    ignore_occluded: bool = False,
) -> dict[str, float]:
    """The headline metrics of predictions against the samples' visible crossings."""
    return summary([truth_of(s, ignore_occluded=ignore_occluded) for s in samples], predictions, sigma=sigma)


def write_predictions(path: str | Path, image_ids: Sequence[str], predictions: Sequence[np.ndarray]) -> Path:
    """One row per prediction: image_id, u, v, score (pixels, COCO corner origin)."""
    ids = [i for i, p in zip(image_ids, predictions, strict=True) for _ in range(len(p))]
    allp = np.concatenate([np.asarray(p, float).reshape(-1, 3) for p in predictions] or [np.zeros((0, 3))])
    columns = {k: pa.array(allp[:, i], pa.float64()) for i, k in enumerate(("u", "v", "score"))}
    table = pa.table({"image_id": pa.array(ids, pa.string()), **columns})
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path)
    return path


def load_splits(root: str | Path, splits: Sequence[str] = SPLITS, *, truth: str = "sight") -> list[Sample]:
    """Every image of ``splits``, in the samples table's order (``truth``: :data:`~.data.TRUTHS`)."""
    return [s for split in splits for s in load_split(root, split, truth=truth)]


def random_frames(root: str | Path, *, seed: int = 0) -> tuple[list[Sample], int]:
    """A test set as a random frame-level split draws one: ``RANDOM_SPLIT_FRACTION`` of all the dataset's
    frames, whatever their scene, and how many of them are in the train split (what a random split leaks)."""
    everything = load_splits(root)
    rng = np.random.default_rng(seed)
    n = max(1, round(RANDOM_SPLIT_FRACTION * len(everything)))
    pick = np.sort(rng.choice(len(everything), size=min(n, len(everything)), replace=False))
    train_ids = {s.image_id for s in load_split(root, "train")}
    drawn = [everything[i] for i in pick]
    return drawn, sum(s.image_id in train_ids for s in drawn)


def set_border_aside(
    samples: Sequence[Sample], predictions: Sequence[np.ndarray], band_px: float
) -> tuple[list[Truth], list[np.ndarray]]:
    """Truths and predictions for scoring the inside of each frame: visible crossings within ``band_px`` of
    the image border become ignore regions and predictions within the band are dropped (a detection there of
    a crossing just outside the frame is not counted false)."""

    def inside(uv: np.ndarray, s: Sample) -> np.ndarray:
        uv = np.asarray(uv, float).reshape(-1, 2)
        return ((uv >= band_px) & (uv <= [s.width - band_px, s.height - band_px])).all(axis=1)

    truths, kept = [], []
    for s, p in zip(samples, predictions, strict=True):
        keep = inside(s.visible, s)
        truths.append(Truth(s.visible[keep], s.box_size_px[keep], s.visible[~keep], s.box_size_px[~keep]))
        p = np.asarray(p, float).reshape(-1, 3)
        kept.append(p[inside(p[:, :2], s)])
    return truths, kept


def breakdown(
    root: str | Path, samples: Sequence[Sample], predictions: Sequence[np.ndarray], *, sigma: float
) -> dict[str, dict[str, float]]:
    """Where a split's misses and false detections lie, row name -> metrics: the frames' inside (crossings
    at least ``BORDER_BAND_PX`` from the border), and the scenes with and without a second mat beneath the
    bars (when the samples table has ``LOWER_MAT_COLUMN``; a group with no image left out)."""
    rows = {
        f"crossings >= {BORDER_BAND_PX:g} px inside the frame": summary(
            *set_border_aside(samples, predictions, BORDER_BAND_PX), sigma=sigma
        )
    }
    table = pq.read_table(Path(root) / "tables/samples.parquet")
    if LOWER_MAT_COLUMN not in table.column_names:
        return rows
    lower = dict(zip(table["image_id"].to_pylist(), table[LOWER_MAT_COLUMN].to_pylist(), strict=True))
    for flag, name in ((True, "scenes with a lower mat"), (False, "scenes without a lower mat")):
        pick = [k for k, s in enumerate(samples) if bool(lower[s.image_id]) == flag]
        if pick:
            rows[name] = score([samples[k] for k in pick], [predictions[k] for k in pick], sigma=sigma)
    return rows


def calibrate_score_bias(samples: Sequence[Sample], predictions: Sequence[np.ndarray]) -> float:
    """The logit shift that puts score 0.5 at the raw score of best F1 (5 px gate) on these samples; ranking,
    AP and recall at any precision are unchanged. Choose it on the validation split."""
    px = pixel_metrics([truth_of(s) for s in samples], predictions, threshold=0.5)
    if not len(px.curve_score) or px.n_gt == 0:
        return 0.0
    p, r = px.curve_precision, px.curve_recall
    f1 = np.where(p + r > 0, 2 * p * r / np.maximum(p + r, 1e-12), 0.0)
    best = int(np.argmax(f1))
    s = np.clip(px.curve_score, 1e-6, 1 - 1e-6)
    logit = np.log(s / (1 - s))
    cut = logit[best] if best + 1 == len(logit) else 0.5 * (logit[best] + logit[best + 1])
    return float(np.clip(-cut, -MAX_SCORE_BIAS, MAX_SCORE_BIAS))


@contextmanager
def first_stage_only(detector: Detector) -> Iterator[Detector]:
    """Within the block, ``detector.detect`` gives its first stage's detections alone."""
    stages = detector.refiner, detector.depth_check, detector.line_check
    detector.refiner = detector.depth_check = detector.line_check = None
    try:
        yield detector
    finally:
        detector.refiner, detector.depth_check, detector.line_check = stages
