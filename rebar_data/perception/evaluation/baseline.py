"""A YOLOv8n-pose-shaped network, for latency comparison only (random weights, never trained here).

It has the layers of Ultralytics' YOLOv8n-pose (width 0.25, depth 0.33): a CSP-Darknet backbone with C2f
blocks and SPPF, a PAN neck, and decoupled box (DFL), class and keypoint heads at strides 8, 16 and 32, so
timing it beside our detector in the same run, on the same runtime, shows what the generic design costs on
this CPU. Box decoding and NMS are left out, which flatters it.
"""

from __future__ import annotations

import torch
from torch import nn


class Conv(nn.Sequential):
    def __init__(self, cin: int, cout: int, k: int = 1, s: int = 1):
        super().__init__(nn.Conv2d(cin, cout, k, s, k // 2, bias=False), nn.BatchNorm2d(cout), nn.SiLU())


class Bottleneck(nn.Module):
    def __init__(self, c: int, shortcut: bool):
        super().__init__()
        self.cv1, self.cv2, self.add = Conv(c, c, 3), Conv(c, c, 3), shortcut

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.cv2(self.cv1(x))
        return x + y if self.add else y


class C2f(nn.Module):
    def __init__(self, cin: int, cout: int, n: int, shortcut: bool):
        super().__init__()
        self.c = cout // 2
        self.cv1 = Conv(cin, 2 * self.c)
        self.m = nn.ModuleList(Bottleneck(self.c, shortcut) for _ in range(n))
        self.cv2 = Conv((2 + n) * self.c, cout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = list(self.cv1(x).chunk(2, 1))
        for m in self.m:
            y.append(m(y[-1]))
        return self.cv2(torch.cat(y, 1))


class SPPF(nn.Module):
    def __init__(self, cin: int, cout: int, k: int = 5):
        super().__init__()
        c = cin // 2
        self.cv1, self.cv2 = Conv(cin, c), Conv(4 * c, cout)
        self.m = nn.MaxPool2d(k, 1, k // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = [self.cv1(x)]
        for _ in range(3):
            y.append(self.m(y[-1]))
        return self.cv2(torch.cat(y, 1))


class YoloPoseLike(nn.Module):
    """Image (N, 3, H, W) in [0, 1], H and W multiples of 32 -> per-level (box 64 + class 1 + keypoint 3) maps."""

    def __init__(self, *, keypoint_channels: int = 3):
        super().__init__()
        self.b0 = nn.Sequential(
            Conv(3, 16, 3, 2),
            Conv(16, 32, 3, 2),
            C2f(32, 32, 1, True),
            Conv(32, 64, 3, 2),
            C2f(64, 64, 2, True),
        )
        self.b1 = nn.Sequential(Conv(64, 128, 3, 2), C2f(128, 128, 2, True))
        self.b2 = nn.Sequential(Conv(128, 256, 3, 2), C2f(256, 256, 1, True), SPPF(256, 256))
        self.up = nn.Upsample(scale_factor=2.0, mode="nearest")
        self.n4 = C2f(384, 128, 1, False)
        self.n3 = C2f(192, 64, 1, False)
        self.d3, self.p4 = Conv(64, 64, 3, 2), C2f(192, 128, 1, False)
        self.d4, self.p5 = Conv(128, 128, 3, 2), C2f(384, 256, 1, False)
        self.heads = nn.ModuleList(
            nn.ModuleList(
                [
                    nn.Sequential(Conv(c, 64, 3), Conv(64, 64, 3), nn.Conv2d(64, 64, 1)),
                    nn.Sequential(Conv(c, 64, 3), Conv(64, 64, 3), nn.Conv2d(64, 1, 1)),
                    nn.Sequential(Conv(c, 16, 3), Conv(16, 16, 3), nn.Conv2d(16, keypoint_channels, 1)),
                ]
            )
            for c in (64, 128, 256)
        )

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        p3 = self.b0(x)
        p4 = self.b1(p3)
        p5 = self.b2(p4)
        t4 = self.n4(torch.cat([self.up(p5), p4], 1))
        o3 = self.n3(torch.cat([self.up(t4), p3], 1))
        o4 = self.p4(torch.cat([self.d3(o3), t4], 1))
        o5 = self.p5(torch.cat([self.d4(o4), p5], 1))
        return [torch.cat([h(o) for h in hs], 1) for o, hs in zip((o3, o4, o5), self.heads, strict=True)]
