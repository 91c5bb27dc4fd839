"""Training and model files of the depth check (:mod:`rebar_data.perception.inference.checks`): depth
patches around the visible crossings are its positives, the first stage's false detections
(:func:`~rebar_data.perception.training.refine.negatives_in`) its negatives.

Each epoch every image gives the depth of one sensor: its dataset's own (``sensor_depth/``, for
``dataset_share`` of the images) or one of ``drawn_sensors`` drawn anew, with random parameters, over its
exact depth, so the check learns what every camera's holes, noise and misregistration look like."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import Sample, sample_depth
from rebar_data.perception.inference.checks import MM_PER_M, encode_depth
from rebar_data.perception.networks.stages import DepthNet
from rebar_data.perception.training.config import DepthCheckConfig
from rebar_data.perception.training.later_stages import StageFile, classed_rightly, count_classes, train_stage
from rebar_data.perception.training.refine_data import patch_keys, steps_per_epoch
from rebar_data.render.depth_sensor import sense_depth
from rebar_data.scene.config import DepthSensorConfig
from rebar_data.scene.sample import sample_depth_sensor


def build(cfg: DepthCheckConfig) -> DepthNet:
    """The network these settings describe."""
    return DepthNet(cfg.patch_px, cfg.widths, cfg.hidden)


FILE = StageFile(
    "rebar-keypoint-depth-check",
    "depth-check",
    DepthCheckConfig,
    "depth_check_config",
    build,
    frozenset({"veto_power", "veto_margin", "threads"}),
)
save, load = FILE.save, FILE.load


def check_depth(samples: list[Sample]) -> None:
    """Raise ConfigError unless every sample has its depth image."""
    missing = [s for s in samples if s.depth_path is None]
    if missing:
        raise ConfigError(
            f"{missing[0].path}: has no depth image beside it ({len(missing)} of {len(samples)} training "
            "images lack one); accepted: a dataset with its depth/ folder, or depth_check: {enabled: false}"
        )


class PaddedDepth:
    """A depth image as uint16 millimetres, mirrored beyond its border once, so that ``patch(centre)`` (in
    metres, as :func:`~rebar_data.perception.inference.refine.patches` cuts it) is a slice."""

    def __init__(self, depth_m: np.ndarray, size: int):
        half = size // 2
        self.size = size
        self.height, self.width = depth_m.shape
        mm = np.clip(np.rint(depth_m * MM_PER_M), 0, 65535).astype(np.uint16)
        self._padded = cv2.copyMakeBorder(mm, half, half, half, half, cv2.BORDER_REFLECT)

    def patch(self, centre: np.ndarray) -> np.ndarray:
        u, v = np.clip(np.floor(np.asarray(centre, float) + 0.5), 0, [self.width, self.height]).astype(int)
        return self._padded[v : v + self.size, u : u + self.size].astype(np.float32) / MM_PER_M


def epoch_depth(s: Sample, index: int, epoch: int, cfg: DepthCheckConfig, *, seed: int) -> np.ndarray:
    """Sample ``s``'s (the ``index``-th) depth image in ``epoch``: its dataset's sensor depth, or a drawn
    sensor's image of its exact depth (from a generator seeded by (seed, epoch, index) alone)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7933, epoch, index]))
    own = rng.random() < cfg.dataset_share and s.sensor_depth_path is not None
    if own or not cfg.drawn_sensors:
        return sample_depth(s, "sensor")
    model = cfg.drawn_sensors[int(rng.integers(len(cfg.drawn_sensors)))]
    sensor = sample_depth_sensor(DepthSensorConfig(models={model: 1.0}), rng)
    return sense_depth(sample_depth(s, "exact"), sensor, rng, fx=s.camera[0])


def depth_batches(
    depths: Callable[[int], list[PaddedDepth]],
    samples: list[Sample],
    negatives: list[np.ndarray],
    cfg: DepthCheckConfig,
    *,
    seed: int,
    first: int,
) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """Every batch of epochs ``first`` to ``cfg.epochs``: encoded patches (B, 2, P, P) and whether each
    shows a crossing (B,), cut from ``depths(epoch)``. Each epoch's from a generator seeded by (seed, epoch)
    alone."""
    keys = patch_keys(samples, negatives)
    steps = steps_per_epoch(samples, negatives, cfg)
    for epoch in range(first, cfg.epochs + 1):
        rng = np.random.default_rng(np.random.SeedSequence([seed, 7927, epoch]))
        images = depths(epoch)
        order = rng.permutation(len(keys))
        for b in range(steps):
            rows = keys[order[b * cfg.batch_size : (b + 1) * cfg.batch_size]]
            jitter = rng.normal(0.0, cfg.jitter_px, (len(rows), 2))
            cut = np.empty((len(rows), cfg.patch_px, cfg.patch_px), np.float32)
            for j, (i, k, positive) in enumerate(rows):
                centre = samples[i].visible[k] if positive else negatives[i][k]
                cut[j] = images[i].patch(centre + jitter[j])
            turns = rng.integers(0, 4, len(rows))
            flips = rng.uniform(size=len(rows)) < 0.5
            for t in range(1, 4):
                cut[turns == t] = np.rot90(cut[turns == t], t, axes=(1, 2))
            cut[flips] = cut[flips][:, :, ::-1]
            x, _ = encode_depth(
                cut, scale_m=cfg.scale_m, clip=cfg.clip, gain=rng.uniform(*cfg.gain, len(rows))
            )
            yield torch.from_numpy(x), torch.from_numpy(rows[:, 2].astype(np.float32))


def train_depth_check(
    samples: list[Sample],
    negatives: list[np.ndarray] | Callable[[], list[np.ndarray]],
    out: Path,
    cfg: DepthCheckConfig,
    *,
    seed: int,
    data: list[str] | None = None,
    progress: bool = False,
    init: DepthNet | None = None,
    device: torch.device | str = "cpu",
) -> tuple[DepthNet, list[dict[str, float]]]:
    """Train the depth check on depth images of ``samples`` (:func:`epoch_depth`; their exact depth where a
    dataset has no sensor depth and ``cfg`` draws none), resumable in ``out/depth_last.pt``; returns it and one row per epoch. ``negatives`` (each sample's
    (M, 2) points) may be a function giving them, called only when there is training; ``data``: whence;
    ``init``: trained weights to start from."""
    check_depth(samples)
    torch.manual_seed(seed)

    def prepare(payload, first):
        found = negatives() if callable(negatives) else negatives

        def depths(epoch: int) -> list[PaddedDepth]:
            each = tqdm(
                samples, desc=f"depth images {epoch}", disable=not progress, leave=False, file=sys.stderr
            )
            return [
                PaddedDepth(epoch_depth(s, i, epoch, cfg, seed=seed), cfg.patch_px)
                for i, s in enumerate(each)
            ]

        batches = depth_batches(depths, samples, found, cfg, seed=seed, first=first)
        return batches, steps_per_epoch(samples, found, cfg), {}

    def loss(net, batch, tally):
        x, y = batch
        logit = net(x)
        count_classes(tally, logit, y.bool())
        return F.binary_cross_entropy_with_logits(logit, y)

    def summary(tally, steps):
        n, p = classed_rightly(tally)
        return {"loss": tally["loss"] / steps, "negatives_right": n, "positives_right": p}

    def describe(row):
        return (
            f"loss {row['loss']:.4f}; classed rightly: {row['positives_right']:.1%} of crossings, "
            f"{row['negatives_right']:.1%} of negatives"
        )

    return train_stage(
        FILE,
        build(cfg),
        cfg,
        out / "depth_last.pt",
        name="depth check",
        data=data,
        prepare=prepare,
        loss=loss,
        summary=summary,
        describe=describe,
        progress=progress,
        init=init,
        device=device,
    )
