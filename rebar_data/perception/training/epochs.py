"""The first stage's training epochs, for the run and its adapt epochs: the augmented batches (the same in a
loader process and after a resume), the learning-rate schedule, the step loop, the weights' moving average."""

from __future__ import annotations

import copy
import math
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import Sample, per_file, read_distractors, read_image, read_images
from rebar_data.perception.inference.detector import STRIDE
from rebar_data.perception.inference.image import focal_scale
from rebar_data.perception.networks.keypoint_net import KeypointNet
from rebar_data.perception.training.augment import Source, mosaic_crop, photometric, single_crop
from rebar_data.perception.training.config import TrainConfig
from rebar_data.perception.training.loss import detection_loss
from rebar_data.perception.training.targets import encode_targets


class WeightAverage:
    """Exponential moving average of a network's weights; the ramp lets it follow the fast early epochs."""

    def __init__(self, net: torch.nn.Module, *, decay: float = 0.998, ramp_steps: float = 300.0):
        self.net = copy.deepcopy(net).eval()
        for p in self.net.parameters():
            p.requires_grad_(False)
        self.decay, self.ramp_steps, self.updates = decay, ramp_steps, 0

    @torch.no_grad()
    def update(self, net: torch.nn.Module) -> None:
        self.updates += 1
        d = self.decay * (1 - math.exp(-self.updates / self.ramp_steps))
        src = net.state_dict()
        for k, v in self.net.state_dict().items():
            if v.dtype.is_floating_point:
                v.mul_(d).add_(src[k].detach(), alpha=1 - d)
            else:
                v.copy_(src[k])


def restore(payload: dict[str, Any], net: torch.nn.Module, avg: WeightAverage, opt: torch.optim.Optimizer):
    """Load a checkpoint's weights, weight average, optimiser and random state; returns its run state."""
    net.load_state_dict(payload["state_dict"])
    avg.net.load_state_dict(payload["average_state_dict"])
    avg.updates = payload["average_updates"]
    opt.load_state_dict(payload["optimizer"])
    torch.set_rng_state(payload["torch_rng"])
    return payload["state"]


def checkpoint_state(
    net: torch.nn.Module, avg: WeightAverage, opt: torch.optim.Optimizer, state: dict[str, Any]
):
    """What a checkpoint keeps beside ``net``'s weights so that :func:`restore` goes on where it stopped."""
    return {
        "average_state_dict": avg.net.state_dict(),
        "average_updates": avg.updates,
        "optimizer": opt.state_dict(),
        "torch_rng": torch.get_rng_state(),
        "state": state,
    }


class TrainingImages:
    """The training images (decoded once per file when caching) and their crossings; with ``distractors``,
    each image's distractor pixels (for ``AugmentConfig.distractor_gain``)."""

    def __init__(
        self,
        samples: list[Sample],
        *,
        cache: bool,
        occluded: str,
        distractors: bool = False,
        focal_px: float | None = None,
    ):
        self.samples = samples
        # each image's crops drawn at the focal length focal_px (None: as it comes), as the detector reads it
        self.gains = [1.0 if s.camera is None else focal_scale(focal_px, s.intrinsics) for s in samples]
        self.ignore_occluded = occluded == "ignore"
        self.images = read_images(samples) if cache else None
        self.distractors = distractors
        self.masks = per_file(samples, read_distractors) if distractors and cache else None

    def pick(self, rng: np.random.Generator) -> Source:
        k = int(rng.integers(len(self.samples)))
        s = self.samples[k]
        image = self.images[k] if self.images is not None else read_image(s.path)
        mask = (
            (self.masks[k] if self.masks is not None else read_distractors(s)) if self.distractors else None
        )
        ignore = s.occluded if self.ignore_occluded else np.zeros((0, 2))
        return Source(image, s.visible, ignore, s.camera, mask, self.gains[k])


def make_batch(
    data: TrainingImages, rng: np.random.Generator, cfg: TrainConfig, *, mosaic: bool
) -> tuple[torch.Tensor, ...]:
    """One augmented batch: images (B, 3, S, S), rays and the targets (heat, offset and their weights)."""
    size, aug = cfg.crop_px, cfg.augment
    cells = size // STRIDE
    rows = []
    for _ in range(cfg.batch_size):
        if mosaic and rng.uniform() < aug.mosaic_probability:
            crop = mosaic_crop(lambda: data.pick(rng), rng, size=size, cfg=aug)
        else:
            crop = single_crop(data.pick(rng), rng, size=size, cfg=aug)
        targets = encode_targets(
            crop.positives, crop.ignore, cells, cells, sigma_cells=cfg.heatmap_sigma_cells
        )
        rows.append((photometric(crop.image, rng, aug), crop.rays, *targets))
    images, *rest = (np.stack(a) for a in zip(*rows, strict=True))
    return (torch.from_numpy(images).permute(0, 3, 1, 2).float(), *(torch.from_numpy(a) for a in rest))


@dataclass
class BatchStream(torch.utils.data.IterableDataset):
    """Every batch of epochs ``first`` to ``last``, each epoch's from a generator seeded by (seed, epoch)
    alone; it holds the samples' labels and paths, and reads the images where it runs."""

    samples: list[Sample]
    cfg: TrainConfig
    first: int
    last: int
    steps: int
    focal_px: float | None = None

    def __iter__(self):
        data = TrainingImages(
            self.samples,
            cache=self.cfg.cache_images,
            occluded=self.cfg.occluded,
            distractors=self.cfg.augment.scales_distractors,
            focal_px=self.focal_px,
        )
        for epoch in range(self.first, self.last + 1):
            rng = np.random.default_rng(np.random.SeedSequence([self.cfg.seed, epoch]))
            mosaic = epoch <= self.cfg.augment.mosaic_epochs
            for _ in range(self.steps):
                yield make_batch(data, rng, self.cfg, mosaic=mosaic)


def _loader_worker_init(_: int) -> None:
    import cv2

    torch.set_num_threads(1)
    cv2.setNumThreads(1)


def batch_stream(
    samples: list[Sample],
    cfg: TrainConfig,
    *,
    first: int,
    last: int,
    steps: int,
    focal_px: float | None = None,
):
    """An iterator over :class:`BatchStream`'s batches, each image's crops drawn at the focal length
    ``focal_px`` (None: as it comes). With ``loader_workers`` = 1 they are made in a second process
    (spawned: OpenCV's and OpenMP's thread pools do not survive a fork) while the network trains."""
    stream = BatchStream(samples, cfg, first, last, steps, focal_px)
    if cfg.loader_workers == 0:
        return iter(stream)
    return iter(
        torch.utils.data.DataLoader(
            stream,
            batch_size=None,
            num_workers=1,
            prefetch_factor=4,
            worker_init_fn=_loader_worker_init,
            multiprocessing_context="spawn",
        )
    )


DEVICES = ("auto", "cpu", "cuda")  # what --device takes


def training_device(name: str = "auto") -> torch.device:
    """The device ``name`` trains on: ``auto`` is the GPU where PyTorch sees one, else the CPU; ConfigError
    for a name not in :data:`DEVICES`, or ``cuda`` where there is none."""
    if name not in DEVICES:
        raise ConfigError(f"--device {name!r} is not accepted; accepted: one of {', '.join(DEVICES)}")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: PyTorch sees no GPU here; accepted: --device cpu or auto")
    return torch.device("cuda" if name != "cpu" and torch.cuda.is_available() else "cpu")


def warmup_cosine(step: int, *, peak: float, warm: float, total: float) -> float:
    """Linear warm-up over the first ``warm`` steps, then cosine decay to 2% of ``peak`` at ``total``."""
    if step < warm:
        return peak * (step + 1) / warm
    t = min(1.0, (step - warm) / max(1.0, total - warm))
    return peak * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * t)))


def batch_bar(steps: int, desc: str, *, progress: bool) -> tqdm:
    """The progress bar over an epoch's ``steps`` batches (on stderr, gone when done)."""
    return tqdm(range(steps), desc=desc, unit="batch", disable=not progress, leave=False, file=sys.stderr)


def train_epoch(
    net: KeypointNet,
    avg: WeightAverage,
    opt: torch.optim.Optimizer,
    batches: Iterator[tuple[torch.Tensor, ...]],
    cfg: TrainConfig,
    state: dict[str, Any],
    *,
    epoch: int,
    steps: int,
    progress: bool,
    frozen_norm: bool = False,
    device: torch.device | str = "cpu",
) -> dict[str, Any]:
    """One epoch of ``steps`` batches; ``state["step"]`` counts the steps (the learning rate's clock).
    ``frozen_norm`` keeps the batch norms in eval mode, normalising by their running statistics and keeping
    them: for epochs that go on from trained weights with other data. ``net``, ``avg`` and ``opt`` live on
    ``device``; the batches are moved there."""
    mosaic = epoch <= cfg.augment.mosaic_epochs
    net.train()
    for m in net.modules() if frozen_norm else ():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.eval()
    t0 = time.perf_counter()
    sums = np.zeros(3)
    bar = batch_bar(steps, f"epoch {epoch}/{cfg.epochs}", progress=progress)
    lr, warm = cfg.lr, cfg.warmup_epochs * steps
    for _ in bar:
        lr = warmup_cosine(state["step"], peak=cfg.lr, warm=warm, total=cfg.epochs * steps)
        for g in opt.param_groups:
            g["lr"] = lr
        x, rays, heat, hw, off, ow = (t.to(device, non_blocking=True) for t in next(batches))
        x = x.contiguous(memory_format=torch.channels_last)
        total, h, o = detection_loss(net(x, rays), heat, hw, off, ow, offset_weight_factor=cfg.offset_weight)
        opt.zero_grad(set_to_none=True)
        total.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
        opt.step()
        avg.update(net)
        state["step"] += 1
        sums += [total.item(), h.item(), o.item()]
        bar.set_postfix(loss=f"{total.item():.3f}", mosaic=mosaic)
    seconds = time.perf_counter() - t0
    return {
        "epoch": epoch,
        "lr": lr,
        "mosaic": int(mosaic),
        "steps": steps,
        "train_loss": sums[0] / steps,
        "train_heat_loss": sums[1] / steps,
        "train_offset_loss": sums[2] / steps,
        "train_seconds": seconds,
        "crops_per_second": steps * cfg.batch_size / seconds,
    }
