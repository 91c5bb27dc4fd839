"""The second stage's training patches: cut around a labelled crossing or a mined negative with a random
error of the centre, turned, flipped and scaled by the first stage's similarity maps, recoloured a batch at
once; each epoch's from a generator seeded by (seed, epoch) alone."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import cv2
import numpy as np
import torch

from rebar_data.perception.evaluation.data import Sample, per_file_lazily, read_distractors, read_sample_image
from rebar_data.perception.training import augment
from rebar_data.perception.training.config import AugmentConfig, RefineConfig

# uint8 patches, offsets, has an offset (a labelled crossing), is a crossing in the frame (verification)
Batch = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def patch_geometry(cfg: RefineConfig, aug: AugmentConfig) -> AugmentConfig:
    """The turns, flips and scales of the second stage's patches: the crops' with its own ``scale``."""
    return aug.model_copy(update={"scale": cfg.scale})


def training_patch(
    image: np.ndarray,
    crossing: np.ndarray,
    rng: np.random.Generator,
    cfg: RefineConfig,
    geometry: AugmentConfig,
    *,
    uniform: bool = True,
    distractors: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """One patch around ``crossing`` before colour changes (a fourth channel 255 where it shows the image),
    the crossing's offset from its centre and the patch's scale. ``uniform = False`` draws the centre's
    error from the Gaussian alone (for a mined negative); the ``distractors`` pixels get
    ``AugmentConfig.distractor_gain``'s factor; a ``cfg.border_fraction`` of patches get a straight border of
    their own within ``cfg.border_reach_px`` of the crossing."""
    # first: the patch's other draws stay those without it
    gain = augment.draw_gain(rng, geometry, distractors)
    if uniform and rng.uniform() < cfg.jitter_uniform_fraction:
        error = rng.uniform(-cfg.jitter_uniform_px, cfg.jitter_uniform_px, 2)
    else:
        error = rng.normal(0.0, cfg.jitter_px, 2)
    size = cfg.patch_px
    patch_from_image = augment.random_affine(
        rng, centre=np.asarray(crossing, float) + error, target=np.array([size / 2, size / 2]), cfg=geometry
    )
    offset = augment.apply_affine(crossing, patch_from_image)[0] - size / 2
    scale = float(np.sqrt(abs(np.linalg.det(patch_from_image[:, :2]))))
    if gain is not None:
        image, patch_from_image = _gained_around(image, distractors, patch_from_image, size, gain)
    c = np.arange(size) + 0.5  # the patch's pixel centres, mapped into the image
    qx, qy = np.meshgrid(c, c, indexing="xy")
    inv = cv2.invertAffineTransform(patch_from_image)
    u = inv[0, 0] * qx + inv[0, 1] * qy + inv[0, 2]
    v = inv[1, 0] * qx + inv[1, 1] * qy + inv[1, 2]
    on_image = (u >= 0) & (u < image.shape[1]) & (v >= 0) & (v < image.shape[0])
    if rng.uniform() < cfg.border_fraction:  # the side kept holds the patch centre
        axis = int(rng.integers(2))
        at = (size / 2 + offset)[axis] + rng.uniform(-cfg.border_reach_px, cfg.border_reach_px)
        keep = c < at if at > size / 2 else c > at
        on_image &= keep[None, :] if axis == 0 else keep[:, None]
    x = augment.warp(image, patch_from_image, size, fill=0.0)
    x[~on_image] = 0
    x = np.concatenate([x, (on_image * np.uint8(255))[..., None]], axis=2)
    return x, offset, scale


def _gained_around(
    image: np.ndarray, distractors: np.ndarray, patch_from_image: np.ndarray, size: int, gain: float
) -> tuple[np.ndarray, np.ndarray]:
    """The part of ``image`` that the ``size`` square patch of ``patch_from_image`` reads, a margin wider, its
    distractors scaled by ``gain`` (cheaper than the whole frame's), and its map to the patch."""
    corners = np.array([[0, 0], [size, 0], [0, size], [size, size]], float)
    pts = augment.apply_affine(corners, cv2.invertAffineTransform(patch_from_image))
    h, w = image.shape[:2]
    x0, y0 = np.clip(np.floor(pts.min(0)).astype(int) - 2, 0, [w - 1, h - 1])
    x1, y1 = np.clip(np.ceil(pts.max(0)).astype(int) + 2, [x0 + 1, y0 + 1], [w, h])
    part = augment.scaled_where(image[y0:y1, x0:x1], distractors[y0:y1, x0:x1], gain)
    patch_from_part = patch_from_image.copy()
    patch_from_part[:, 2] += patch_from_image[:, :2] @ [x0, y0]
    return part, patch_from_part


def patch_keys(samples: list[Sample], negatives: list[np.ndarray]) -> np.ndarray:
    """(K, 3) rows of (sample, index, is a crossing): the visible crossings first, then the negatives."""
    pos = [(i, k, 1) for i, s in enumerate(samples) for k in range(len(s.visible))]
    neg = [(i, m, 0) for i, n in enumerate(negatives) for m in range(len(n))]
    return np.array(pos + neg, np.int64).reshape(-1, 3)


def steps_per_epoch(samples: list[Sample], negatives: list[np.ndarray], cfg: RefineConfig) -> int:
    """Batches an epoch over every row of :func:`patch_keys` (the last batch may be smaller)."""
    rows = sum(len(s.visible) for s in samples) + sum(len(n) for n in negatives)
    return -(-rows // cfg.batch_size)


def patch_batch(
    rows: np.ndarray,
    image_of: Callable[[int], np.ndarray],
    samples: list[Sample],
    negatives: list[np.ndarray],
    rng: np.random.Generator,
    cfg: RefineConfig,
    aug: AugmentConfig,
    distractors_of: Callable[[int], np.ndarray | None] | None = None,
) -> Batch:
    """The augmented patches of ``rows`` (from :func:`patch_keys`): (B, P, P, C) uint8; (B, 2) offsets of the
    crossing from the centre (with ``cfg.size`` a third column, the log of its box side over the patch's);
    (B,) whether each is around a labelled crossing; (B,) whether that crossing lies on the image the patch
    shows (the verification's label). ``distractors_of`` gives a sample's distractor pixels (or None)."""
    geometry = patch_geometry(cfg, aug)
    xs, ys = [], []
    for i, k, positive in rows:
        centre = samples[i].visible[k] if positive else negatives[i][k]
        mask = distractors_of(i) if distractors_of is not None else None
        x, y, scale = training_patch(
            image_of(i), centre, rng, cfg, geometry, uniform=bool(positive), distractors=mask
        )
        xs.append(x)
        if cfg.size:
            # a negative shows no crossing to size: its 0 never trains (the loss takes labelled crossings)
            box = samples[i].box_size_px[k] * scale if positive else cfg.patch_px
            y = np.append(y, np.log(box / cfg.patch_px))
        ys.append(y)
    x, y = np.stack(xs), np.stack(ys)
    positive = rows[:, 2].astype(bool)
    crossing = positive.copy()
    # colour, blur and noise; what lies beyond the border stays 0
    x[..., :3] = augment.photometric_batch(np.ascontiguousarray(x[..., :3]), rng, aug) * (x[..., 3:4] > 0)
    # a crossing beyond the frame's edge: its offset still trains, its verification learns "no"
    size = x.shape[1]
    j, i = np.clip(np.floor(size / 2 + y[:, :2]).astype(np.int64), 0, size - 1).T
    crossing &= x[np.arange(len(x)), i, j, 3] > 0
    return tuple(torch.from_numpy(a) for a in (x, y.astype(np.float32), positive, crossing))


def patch_batches(
    samples: list[Sample],
    negatives: list[np.ndarray],
    cfg: RefineConfig,
    aug: AugmentConfig,
    *,
    seed: int,
    first: int,
    images: list[np.ndarray] | None = None,
) -> Iterator[Batch]:
    """Every batch of the second stage's epochs ``first`` to ``cfg.epochs``, each epoch's from a generator
    seeded by (seed, epoch) alone. Without ``images`` each file is read once, when first needed."""
    image_of = (lambda i: images[i]) if images is not None else per_file_lazily(samples, read_sample_image)
    distractors_of = per_file_lazily(samples, read_distractors) if aug.scales_distractors else None
    keys = patch_keys(samples, negatives)
    size = cfg.batch_size
    steps = steps_per_epoch(samples, negatives, cfg)
    for epoch in range(first, cfg.epochs + 1):
        rng = np.random.default_rng(np.random.SeedSequence([seed, 7919, epoch]))
        order = rng.permutation(len(keys))
        for b in range(steps):
            rows = keys[order[b * size : (b + 1) * size]]
            yield patch_batch(rows, image_of, samples, negatives, rng, cfg, aug, distractors_of)
