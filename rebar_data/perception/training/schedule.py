"""The learning-rate schedule both detector stages train with."""

from __future__ import annotations

import math

FLOOR = 0.02  # the cosine decays to this fraction of the peak


def warmup_cosine(step: int, *, peak: float, warm: float, total: float) -> float:
    """Linear warm-up over the first ``warm`` steps, then cosine decay to ``FLOOR`` of ``peak`` at ``total``."""
    if step < warm:
        return peak * (step + 1) / warm
    t = min(1.0, (step - warm) / max(1.0, total - warm))
    return peak * (FLOOR + (1.0 - FLOOR) * 0.5 * (1 + math.cos(math.pi * t)))
