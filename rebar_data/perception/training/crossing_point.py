"""Training and model files of the crossing-point stage (:mod:`rebar_data.perception.inference.refine`).

It trains from the labels alone: for each visible crossing of the training images, the patch around its
sight point and the offset to its projected 3D crossing point. The patches are cut once, wider than the
network's (``context_px``); each batch draws its scale, turns, flips and colour changes."""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import Sample, read_image
from rebar_data.perception.inference.refine import patch_rays, patches
from rebar_data.perception.networks.files import export_onnx
from rebar_data.perception.networks.stages import CrossingNet
from rebar_data.perception.training.augment import photometric_batch
from rebar_data.perception.training.config import AugmentConfig, CrossingPointConfig
from rebar_data.perception.training.later_stages import StageFile, train_stage


def build(cfg: CrossingPointConfig) -> CrossingNet:
    """The network these settings describe."""
    return CrossingNet(cfg.patch_px, cfg.widths, cfg.hidden)


FILE = StageFile(
    "rebar-keypoint-crossing-point",
    "crossing-point",
    CrossingPointConfig,
    "crossing_point_config",
    build,
    frozenset({"threads"}),
)
save, load = FILE.save, FILE.load


class PatchSet:
    """Every training patch, cut once: ``context`` (M, C, C, 3) uint8 around each visible crossing's sight
    point (moved by a Gaussian error), ``offset`` (M, 2) from the patch centre to the projected 3D
    crossing point and ``rays`` (M, 2) of the patch centres."""

    def __init__(self, samples: list[Sample], cfg: CrossingPointConfig, *, seed: int, progress: bool = False):
        rng = np.random.default_rng(np.random.SeedSequence([seed, 5147]))
        context, offset, rays = [], [], []
        for s in tqdm(
            samples, desc="crossing-point patches", disable=not progress, leave=False, file=sys.stderr
        ):
            if s.crossings is None or s.camera is None:
                raise ConfigError(
                    f"{s.path}: its dataset records no 3D crossing points (x_crossing, y_crossing, "
                    "z_crossing and world_from_camera); accepted: a dataset built by this version of "
                    "`rebar dataset build`, or crossing_point: {enabled: false}"
                )
            ok = np.flatnonzero(np.isfinite(s.crossings).all(axis=1) & np.isfinite(s.visible).all(axis=1))
            if not len(ok):
                continue
            if len(ok) > cfg.max_per_image:
                ok = np.sort(rng.choice(ok, cfg.max_per_image, replace=False))
            centre = s.visible[ok] + rng.normal(0.0, cfg.jitter_px, (len(ok), 2))
            cut, corners = patches(read_image(s.path), centre, cfg.context_px)
            context.append(cut)
            # the label's own offset from the sight point: at inference it is added to the refined detection,
            # so the patch centre's error (the detection's, the rounding to a corner) is not this stage's
            offset.append(s.crossings[ok] - s.visible[ok])  # in the patch's pixels
            rays.append(patch_rays(corners, s.intrinsics))
        if not context:
            raise ConfigError(
                "the training images have no visible crossings with a 3D crossing point; accepted: a "
                "dataset with labelled crossings"
            )
        self.context = np.concatenate(context)
        self.offset = np.concatenate(offset).astype(np.float32)
        self.rays = np.concatenate(rays)

    def __len__(self) -> int:
        return len(self.context)


def batches(data: PatchSet, cfg: CrossingPointConfig, aug: AugmentConfig, *, seed: int, epoch: int):
    """One epoch's batches: (B, 3, P, P) float patches, (B, 2) rays, (B, 2) offsets."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 5153, epoch]))
    order = rng.permutation(len(data))
    p, c = cfg.patch_px, cfg.context_px
    for lo in range(0, len(order), cfg.batch_size):
        rows = order[lo : lo + cfg.batch_size]
        n = len(rows)
        scale = np.exp(rng.uniform(np.log(cfg.scale[0]), np.log(cfg.scale[1]), n))
        window = np.clip(2 * np.round(p / scale / 2), 2, c).astype(int)  # even: centred on the corner
        out = np.empty((n, p, p, 3), np.uint8)
        for j, (r, w) in enumerate(zip(rows, window, strict=True)):
            lo_px = c // 2 - w // 2
            crop = data.context[r, lo_px : lo_px + w, lo_px : lo_px + w]
            if w != p:
                crop = cv2.resize(crop, (p, p), interpolation=cv2.INTER_AREA if w > p else cv2.INTER_LINEAR)
            out[j] = crop
        offset = data.offset[rows] * (p / window)[:, None].astype(np.float32)
        rays = data.rays[rows].copy()
        turns = rng.integers(0, 4, n)
        flips = rng.uniform(size=n) < 0.5
        out[flips] = out[flips][:, :, ::-1]  # mirrored left to right: x -> -x
        offset[flips, 0] *= -1
        rays[flips, 0] *= -1
        for t in range(1, 4):  # np.rot90 by t quarter turns: (x, y) -> (y, -x), t times
            pick = turns == t
            out[pick] = np.rot90(out[pick], t, axes=(1, 2))
            for _ in range(t):
                offset[pick] = np.c_[offset[pick, 1], -offset[pick, 0]]
                rays[pick] = np.c_[rays[pick, 1], -rays[pick, 0]]
        out = photometric_batch(out, rng, aug)
        x = torch.from_numpy(out).permute(0, 3, 1, 2).float()
        yield x, torch.from_numpy(rays), torch.from_numpy(offset)


def train_crossing_point(
    samples: list[Sample],
    out: Path,
    cfg: CrossingPointConfig,
    aug: AugmentConfig,
    *,
    seed: int,
    progress: bool = False,
    init: CrossingNet | None = None,
    data: list[str] | None = None,
    device: torch.device | str = "cpu",
) -> tuple[CrossingNet, list[dict[str, float]]]:
    """Train the crossing-point stage on the visible crossings of ``samples``, resumable in
    ``out/crossing_last.pt``; returns the network and one row per epoch (L1 loss in pixels, seconds).
    ``init``: trained weights to start from, ``data`` naming them."""
    torch.manual_seed(seed)
    found: list[PatchSet] = []

    def prepare(payload, first):
        found.append(PatchSet(samples, cfg, seed=seed, progress=progress))
        epochs = range(first, cfg.epochs + 1)
        each = (batches(found[0], cfg, aug, seed=seed, epoch=epoch) for epoch in epochs)
        return itertools.chain.from_iterable(each), -(-len(found[0]) // cfg.batch_size), {}

    def loss(net, batch, tally):
        x, rays, y = batch
        return F.l1_loss(net(x, rays), y)

    return train_stage(
        FILE,
        build(cfg),
        cfg,
        out / "crossing_last.pt",
        name="crossing point",
        data=data,
        prepare=prepare,
        loss=loss,
        summary=lambda tally, steps: {"loss_px": tally["loss"] / steps},
        describe=lambda row: f"L1 {row['loss_px']:.3f} px ({len(found[0])} patches, {row['seconds']:.0f} s)",
        progress=progress,
        init=init,
        device=device,
    )


def attach(
    model: str | Path,
    samples: list[Sample],
    out: Path,
    cfg: CrossingPointConfig,
    aug: AugmentConfig,
    *,
    seed: int,
    progress: bool = False,
) -> Path:
    """Train the crossing-point stage (resumable in ``out``) and put it beside ``model`` as
    ``<stem>.crossing.onnx``, named in the model file's metadata with its SHA-256; returns that file."""
    from rebar_data.digest import sha256_file
    from rebar_data.outputs import replace_file
    from rebar_data.perception.inference.model_file import crossing_point_path
    from rebar_data.perception.networks.files import check_model_file, update_onnx_meta

    model = check_model_file(model)
    out.mkdir(parents=True, exist_ok=True)
    net, history = train_crossing_point(samples, out, cfg, aug, seed=seed, progress=progress)
    save(out / "best.crossing.pt", net, cfg, history=history)
    stage = export_onnx(net, out / "best.crossing.onnx")
    # the stage lands first, so the model never names a missing file
    dst = replace_file(crossing_point_path(model), lambda tmp: tmp.write_bytes(stage.read_bytes()))
    entry = {"patch_px": cfg.patch_px, "sha256": sha256_file(dst)}
    update_onnx_meta(model, {"crossing_point": entry})
    return dst
