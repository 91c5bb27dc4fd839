"""The second stage's training patches (:mod:`rebar_data.perception.training.refine` trains on them).

Each patch is cut around a labelled crossing, or a mined negative, with a random error of its centre,
turned, flipped and scaled with the point by the first stage's similarity maps
(:func:`~rebar_data.perception.training.augment.random_affine`); a batch's colour, blur and noise changes are
drawn for all its patches at once (:func:`~rebar_data.perception.training.augment.photometric_batch`).

Every epoch's batches come from a generator seeded by (seed, epoch) alone, so a resumed run gets the
batches it would have got.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import cv2
import numpy as np
import torch

from rebar_data.perception.evaluation.data import Sample, per_file_lazily, read_distractors, read_sample_image
from rebar_data.perception.training.augment import (
    apply_affine,
    draw_gain,
    photometric_batch,
    random_affine,
    scaled_where,
    warp,
)
from rebar_data.perception.training.config import AugmentConfig, RefineConfig

# uint8 patches, offsets, has an offset (a labelled crossing), is a crossing in the frame (verification)
Batch = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def patch_geometry(cfg: RefineConfig, aug: AugmentConfig) -> AugmentConfig:
    """The turns, flips and scales of the second stage's patches: the crops' settings with the patches'
    own ``scale`` range."""
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
    """One patch around a labelled crossing, before colour changes, the crossing's offset from its
    centre, and how many patch pixels an image pixel became (the patch's scale); ``geometry`` is
    :func:`patch_geometry`'s. ``uniform = False`` draws the centre's error from the
    Gaussian alone (for a mined negative, which a 5 px error could move next to a real crossing). ``distractors`` (H, W bool, the image's
    distractor pixels) get ``AugmentConfig.distractor_gain``'s factor in the patch.

    The patch has a fourth channel, 255 where it shows the image (0 and 0 in
    colour beyond the image's border, as :func:`~rebar_data.perception.inference.refine.patches` cuts them), and a
    ``cfg.border_fraction`` of patches get a border of their own (:func:`_own_edge`)."""
    gain = draw_gain(rng, geometry, distractors)  # first: the patch's other draws stay those without it
    if uniform and rng.uniform() < cfg.jitter_uniform_fraction:
        error = rng.uniform(-cfg.jitter_uniform_px, cfg.jitter_uniform_px, 2)
    else:
        error = rng.normal(0.0, cfg.jitter_px, 2)
    size = cfg.patch_px
    patch_from_image = random_affine(
        rng,
        centre=np.asarray(crossing, float) + error,
        target=np.array([size / 2, size / 2]),
        cfg=geometry,
    )
    offset = apply_affine(crossing, patch_from_image)[0] - size / 2
    scale = float(np.sqrt(abs(np.linalg.det(patch_from_image[:, :2]))))
    if gain is not None:
        image, patch_from_image = _gained_around(image, distractors, patch_from_image, (0.0, size), gain)
    edge = None
    if rng.uniform() < cfg.border_fraction:
        edge = _own_edge(rng, size / 2 + offset, size, cfg.border_reach_px)
    x, on_image = _masked_cut(image, patch_from_image, size, edge)
    x = np.concatenate([x, (on_image * np.uint8(255))[..., None]], axis=2)
    return x, offset, scale


def _gained_around(
    image: np.ndarray,
    distractors: np.ndarray,
    patch_from_image: np.ndarray,
    span: tuple[float, float],
    gain: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The part of ``image`` that the square ``span`` (from, to, in patch pixels) of ``patch_from_image``
    reads (its bounding box, a margin wider, within the image), its distractor pixels scaled by ``gain``,
    and the map from that part to the patch: only the pixels a patch reads are scaled, as the whole
    frame's would cost more than the patch. The part's edges lie on the image's wherever the patch
    reaches beyond it."""
    a, b = span
    corners = np.array([[a, a], [b, a], [a, b], [b, b]], float)
    pts = apply_affine(corners, cv2.invertAffineTransform(patch_from_image))
    h, w = image.shape[:2]
    x0, y0 = np.clip(np.floor(pts.min(0)).astype(int) - 2, 0, [w - 1, h - 1])
    x1, y1 = np.clip(np.ceil(pts.max(0)).astype(int) + 2, [x0 + 1, y0 + 1], [w, h])
    part = scaled_where(image[y0:y1, x0:x1], distractors[y0:y1, x0:x1], gain)
    patch_from_part = patch_from_image.copy()
    patch_from_part[:, 2] += patch_from_image[:, :2] @ [x0, y0]
    return part, patch_from_part


def _masked_cut(
    image: np.ndarray, patch_from_image: np.ndarray, size: int, edge: tuple[int, float, bool] | None
) -> tuple[np.ndarray, np.ndarray]:
    """The ``size`` square ``patch_from_image`` takes ``image`` to, 0 beyond the image's border and beyond
    ``edge`` (:func:`_own_edge`, None for none), and the (size, size) bool of the pixels that show the image."""
    x = warp(image, patch_from_image, size, fill=0.0)
    on_image = _on_image(patch_from_image, size, image.shape[1], image.shape[0])
    if edge is not None:
        on_image &= _edge_keep(edge, size)
    x[~on_image] = 0
    return x, on_image


def _on_image(patch_from_image: np.ndarray, size: int, width: int, height: int) -> np.ndarray:
    """(size, size) bool: which of the patch's pixel centres map inside the image."""
    c = np.arange(size) + 0.5
    qx, qy = np.meshgrid(c, c, indexing="xy")
    inv = cv2.invertAffineTransform(patch_from_image)
    u = inv[0, 0] * qx + inv[0, 1] * qy + inv[0, 2]
    v = inv[1, 0] * qx + inv[1, 1] * qy + inv[1, 2]
    return (u >= 0) & (u < width) & (v >= 0) & (v < height)


def _own_edge(
    rng: np.random.Generator, point: np.ndarray, size: int, reach: float
) -> tuple[int, float, bool]:
    """A random straight edge along a patch axis within ``reach`` of ``point`` (patch pixels): (axis, where
    it lies along that axis, whether the side kept lies below it). The side kept holds the patch centre;
    the other is beyond the frame. At inference a patch is centred on a point inside the frame, so its
    centre is always on the image."""
    axis = int(rng.integers(2))
    edge = point[axis] + rng.uniform(-reach, reach)
    return axis, float(edge), bool(edge > size / 2)


def _edge_keep(edge: tuple[int, float, bool], size: int) -> np.ndarray:
    """(size, size) bool: the side of :func:`_own_edge`'s ``edge`` that is kept."""
    axis, at, below = edge
    c = np.arange(size) + 0.5
    keep = c < at if below else c > at
    return np.broadcast_to(keep[None, :] if axis == 0 else keep[:, None], (size, size))


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
    """The augmented patches of ``rows`` (from :func:`patch_keys`): (B, P, P, C) uint8, their (B, 2)
    offsets of the crossing from the centre (meaningless for negatives; with ``cfg.size`` a third column,
    the log of the crossing's box side in the patch over the patch's side), (B,) whether each is around a
    labelled crossing, and (B,) whether that crossing lies on the image the patch shows (the
    verification's label: with the border mask, not one beyond the patch's own border).

    ``distractors_of`` (per sample, its distractor pixels or None) lets ``aug.distractor_gain`` act."""
    geometry = patch_geometry(cfg, aug)
    xs, ys = [], []
    for i, k, positive in rows:
        centre = samples[i].visible[k] if positive else negatives[i][k]
        x, y, scale = training_patch(
            image_of(i),
            centre,
            rng,
            cfg,
            geometry,
            uniform=bool(positive),
            distractors=distractors_of(i) if distractors_of is not None else None,
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
    _recolour(x, rng, aug)
    # a crossing beyond the frame's edge is no crossing to the labels (as a mined negative just inside a
    # real border, near a crossing just outside it, is not): its offset still trains, its verification
    # learns "no"
    size = x.shape[1]
    j, i = np.clip(np.floor(size / 2 + y[:, :2]).astype(np.int64), 0, size - 1).T
    crossing &= x[np.arange(len(x)), i, j, 3] > 0
    return (
        torch.from_numpy(x),
        torch.from_numpy(y).float(),
        torch.from_numpy(positive),
        torch.from_numpy(crossing),
    )


def _recolour(x: np.ndarray, rng: np.random.Generator, aug: AugmentConfig) -> None:
    """A batch's colour, blur and noise changes, in place; what lies beyond the border stays 0."""
    rgb = photometric_batch(np.ascontiguousarray(x[..., :3]), rng, aug)
    x[..., :3] = rgb * (x[..., 3:4] > 0)


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
    """Every batch of the second stage's epochs ``first`` to ``cfg.epochs``, in order, each epoch's from a
    generator seeded by (seed, epoch) alone; made in the training process. Without ``images`` each image is
    read when first needed."""
    # by file: an image listed more than once is read once
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
