"""Training loss: CenterNet's penalty-reduced focal loss on the heatmap plus L1 on the offsets.

Both are normalised by the number of crossings in the batch, so the loss does not depend on how many
crossings a crop happens to hold. Cells with zero heat weight (around occluded crossings) add nothing."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def heatmap_focal_loss(
    logit: torch.Tensor, target: torch.Tensor, weight: torch.Tensor, *, alpha: float = 2.0, beta: float = 4.0
) -> torch.Tensor:
    """The focal loss of (N, H, W) heatmap ``logit`` against ``target`` (exactly 1 at crossings), each cell
    weighted by ``weight`` (0 = ignore), summed and divided by the number of positive cells (at least 1)."""
    pos = (target >= 1.0).float()
    p = torch.sigmoid(logit)
    log_p = F.logsigmoid(logit)
    log_1mp = F.logsigmoid(-logit)
    pos_loss = -log_p * (1 - p) ** alpha * pos
    neg_loss = -log_1mp * p**alpha * (1 - target) ** beta * (1 - pos)
    n_pos = pos.sum().clamp(min=1.0)
    return ((pos_loss + neg_loss) * weight).sum() / n_pos


def offset_l1_loss(pred: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """L1 distance of (N, 2, H, W) offsets where ``weight`` (N, H, W) is set, per weighted cell."""
    w = weight.unsqueeze(1)
    return ((pred - target).abs() * w).sum() / weight.sum().clamp(min=1.0)


def detection_loss(
    output: torch.Tensor,
    heat: torch.Tensor,
    heat_weight: torch.Tensor,
    offset: torch.Tensor,
    offset_weight: torch.Tensor,
    *,
    offset_weight_factor: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Total, heatmap and offset losses of a batch of network outputs (N, 3, H, W)."""
    h = heatmap_focal_loss(output[:, 0], heat, heat_weight)
    o = offset_l1_loss(output[:, 1:], offset, offset_weight)
    return h + offset_weight_factor * o, h, o
