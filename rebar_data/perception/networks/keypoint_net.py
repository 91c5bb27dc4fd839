"""The keypoint network: a depthwise-separable encoder to stride 16, a top-down decoder back to stride 4,
and a head giving a crossing heatmap and a sub-cell offset per cell (``docs/detector/design.md``)."""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from rebar_data.config import NonNegativeInt, PositiveInt, Strict


class ModelConfig(Strict):
    """Architecture of the keypoint network (recorded in every checkpoint, so a file rebuilds its model)."""

    channels: tuple[PositiveInt, PositiveInt, PositiveInt, PositiveInt] = (16, 32, 64, 128)  # strides 2 to 16
    blocks: tuple[NonNegativeInt, NonNegativeInt, NonNegativeInt] = (1, 2, 4)  # separable, strides 4 to 16
    # each output cell's viewing ray ((u - cx) / fx, (v - cy) / fy) is an input
    ray_channels: Literal[True] = True
    global_context: Literal[True] = True  # the stride-8 features scaled and shifted by a whole-image vector


def conv_bn_relu(cin: int, cout: int, k: int = 3, stride: int = 1, groups: int = 1, dilation: int = 1):
    pad = dilation * (k // 2)
    return nn.Sequential(
        nn.Conv2d(cin, cout, k, stride, pad, dilation=dilation, groups=groups, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class SeparableBlock(nn.Module):
    """Depthwise 3x3 then pointwise 1x1, residual when the shape is kept."""

    def __init__(self, cin: int, cout: int, *, stride: int = 1, dilation: int = 1):
        super().__init__()
        self.depthwise = conv_bn_relu(cin, cin, 3, stride, groups=cin, dilation=dilation)
        self.pointwise = nn.Sequential(nn.Conv2d(cin, cout, 1, bias=False), nn.BatchNorm2d(cout))
        self.residual = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.pointwise(self.depthwise(x))
        return F.relu(y + x if self.residual else y)


class KeypointNet(nn.Module):
    """Image (N, 3, H, W), RGB values 0-255, H and W multiples of 16, and the viewing rays of the output
    cells' centres (N, 2, H/4, W/4) -> (N, 3, H/4, W/4): the heatmap logit and the offset (x, y) of the
    crossing from the cell's centre, in cells. The rays enter the decoder at stride 8 as a learned embedding
    added to the features; the stride-16 features averaged over the image scale and shift the stride-8 ones
    (FiLM), so every crossing's head knows the frame's perspective."""

    def __init__(self, cfg: ModelConfig | None = None):
        super().__init__()
        self.cfg = cfg or ModelConfig()
        c2, c4, c8, c16 = self.cfg.channels
        n4, n8, n16 = self.cfg.blocks
        self.stem = conv_bn_relu(3, c2, 3, 2)
        self.enc4 = nn.Sequential(
            SeparableBlock(c2, c4, stride=2), *[SeparableBlock(c4, c4) for _ in range(n4)]
        )
        self.enc8 = nn.Sequential(
            SeparableBlock(c4, c8, stride=2), *[SeparableBlock(c8, c8) for _ in range(n8)]
        )
        self.enc16 = nn.Sequential(
            SeparableBlock(c8, c16, stride=2),
            *[SeparableBlock(c16, c16, dilation=1 + i % 2) for i in range(n16)],
        )
        self.lat16 = conv_bn_relu(c16, c8, 1)
        self.ray_embed = nn.Conv2d(2, c8, 1)
        self.dec8 = SeparableBlock(c8, c8)
        self.lat8 = conv_bn_relu(c8, c4, 1)
        self.dec4 = SeparableBlock(c4, c4)
        self.head = nn.Sequential(conv_bn_relu(c4, c4, 3, groups=c4), nn.Conv2d(c4, 3, 1))
        nn.init.constant_(self.head[-1].bias, 0.0)
        with torch.no_grad():
            self.head[-1].bias[0] = -4.6  # start near p = 0.01, as CenterNet does, so early losses are sane
        self.context = nn.Sequential(nn.Linear(c16, c16), nn.ReLU(inplace=True), nn.Linear(c16, 2 * c8))
        nn.init.zeros_(self.context[-1].weight)  # start as the identity: scale 1, shift 0
        nn.init.zeros_(self.context[-1].bias)

    def forward(self, image: torch.Tensor, rays: torch.Tensor) -> torch.Tensor:
        x = self.stem(image * (1.0 / 64.0) - 2.0)
        f4 = self.enc4(x)
        f8 = self.enc8(f4)
        f16 = self.enc16(f8)
        f8 = f8 + F.interpolate(self.lat16(f16), scale_factor=2.0, mode="nearest")
        f8 = f8 + self.ray_embed(F.avg_pool2d(rays, 2))  # the mean of 2x2 cell centres: stride 8's
        scale, shift = self.context(f16.mean(dim=(2, 3))).unsqueeze(-1).unsqueeze(-1).chunk(2, dim=1)
        f8 = f8 * (1.0 + scale) + shift
        f8 = self.dec8(f8)
        f4 = self.dec4(f4 + F.interpolate(self.lat8(f8), scale_factor=2.0, mode="nearest"))
        return self.head(f4)


class UInt8Input(nn.Module):
    """Any of the detector's networks as its ONNX file holds it: uint8 images or patches (N, H, W, C) in,
    as the run time cuts them, and the network's other inputs (the viewing rays) passed on as they come."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor, *rest: torch.Tensor) -> torch.Tensor:
        return self.net(x.permute(0, 3, 1, 2).float(), *rest)


def count_parameters(net: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in net.parameters() if p.requires_grad)
