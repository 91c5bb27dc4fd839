"""Seconds spent in named stages, summed over calls: how the benches break a frame's time down."""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager


class StageTimer:
    """Sums wall-clock seconds per stage name; one clock read at each end of a stage, so it stays on."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - t0
            self.calls[name] += 1

    def reset(self) -> None:
        self.seconds.clear()
        self.calls.clear()

    def totals(self) -> dict[str, tuple[float, int]]:
        """``{stage: (seconds, calls)}``, a plain dict that pickles across processes."""
        return {k: (self.seconds[k], self.calls[k]) for k in self.seconds}
