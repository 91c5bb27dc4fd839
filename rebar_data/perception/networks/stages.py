"""The later stages' networks: 3x3 convolutions from full resolution, three halvings to P / 8, then two
fully connected layers. The second stage (:class:`PatchNet`), the depth check (:class:`DepthNet`) and the
crossing-point stage (:class:`CrossingNet`)."""

from __future__ import annotations

import torch
from torch import nn

from rebar_data.perception.networks.keypoint_net import conv_bn_relu


def conv_stack(
    channels: int, widths: tuple[int, int, int, int], blocks: tuple[int, int, int]
) -> nn.Sequential:
    """3x3 convolutions from ``channels`` to ``widths[0]`` at full resolution, then three halvings to the
    other widths, each followed by ``blocks`` more convolutions at its resolution."""
    a, b, c, d = widths
    layers = [conv_bn_relu(channels, a)]
    for cin, cout, n in ((a, b, blocks[0]), (b, c, blocks[1]), (c, d, blocks[2])):
        layers += [conv_bn_relu(cin, cout, stride=2), *[conv_bn_relu(cout, cout) for _ in range(n)]]
    return nn.Sequential(*layers)


def flat_size(patch_px: int, widths: tuple[int, int, int, int]) -> int:
    """The length of :func:`conv_stack`'s output for a ``patch_px`` patch, flattened."""
    return widths[3] * ((patch_px + 7) // 8) ** 2


class PatchNet(nn.Module):
    """(N, 4, P, P) patches, values 0-255 (RGB and the mask of the pixels on the image) -> (N, 2) offset
    (x, y) of the crossing from the patch centre in pixels; with ``verify`` a third column, the logit that
    the patch shows a crossing; with ``size`` a fourth, the log of its box side over the patch's."""

    def __init__(
        self,
        patch_px: int,
        widths: tuple[int, int, int, int],
        hidden: int,
        blocks: tuple[int, int, int] = (1, 1, 1),
        *,
        verify: bool = False,
        size: bool = False,
    ):
        super().__init__()
        self.patch_px = patch_px
        self.verify = verify
        self.size = size
        self.features = conv_stack(self.channels, widths, blocks)
        self.head = nn.Sequential(
            nn.Flatten(),
            nn.Linear(flat_size(patch_px, widths), hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, 2 + int(verify) + int(size)),
        )

    channels = 4  # RGB and the mask of the pixels on the image

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(patches * (1.0 / 64.0) - 2.0))


class DepthNet(nn.Module):
    """(N, 2, P, P) encoded depth patches (:func:`~rebar_data.perception.inference.checks.encode`) -> (N,)
    logit that the patch shows a crossing."""

    def __init__(self, patch_px: int, widths: tuple[int, int, int, int], hidden: int):
        super().__init__()
        self.patch_px = patch_px
        self.features = conv_stack(2, widths, (0, 0, 0))
        n = flat_size(patch_px, widths)
        self.head = nn.Sequential(
            nn.Flatten(), nn.Linear(n, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 1)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))[:, 0]


class CrossingNet(nn.Module):
    """(N, 3, P, P) patches, values 0-255, and (N, 2) viewing rays -> (N, 2) offset (x, y) in pixels from
    the patch centre's sight point to the projected 3D crossing point."""

    def __init__(self, patch_px: int, widths: tuple[int, int, int, int], hidden: int):
        super().__init__()
        self.patch_px = patch_px
        self.features = conv_stack(3, widths, (1, 1, 0))
        n = flat_size(patch_px, widths) + 2  # and the ray
        self.head = nn.Sequential(nn.Linear(n, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 2))

    def forward(self, patches: torch.Tensor, rays: torch.Tensor) -> torch.Tensor:
        f = self.features(patches * (1.0 / 64.0) - 2.0).flatten(1)
        return self.head(torch.cat([f, rays], dim=1))
