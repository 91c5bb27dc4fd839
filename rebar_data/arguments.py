"""Argument types the commands share."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


class bounded:
    """An argparse ``type`` for a number within bounds, such as ``bounded(int, 1)`` for 1, 2, 3, ...

    ``low`` and ``high`` are inclusive (None: no bound). ``str()`` gives the accepted range in words, for
    the flag's help, so the help and the check say the same thing. A value outside is argparse's error: a
    usage line and one line naming the flag, the value and the range, exit status 2.
    """

    def __init__(
        self, kind: Callable[[str], int | float], low: float | None = None, high: float | None = None
    ):
        self.kind = kind
        self.low = low
        self.high = high
        self.__name__ = kind.__name__  # argparse names the type by it in its own messages

    def __str__(self) -> str:
        noun = "an integer" if self.kind is int else "a number"
        low, high = (
            None if x is None else f"{x:d}" if self.kind is int else f"{x:g}" for x in (self.low, self.high)
        )
        if low is not None and high is not None:
            return f"{noun} from {low} to {high}"
        if low is not None:
            return f"{noun} >= {low}"
        return f"{noun} <= {high}" if high is not None else noun

    def __call__(self, text: str) -> int | float:
        try:
            value = self.kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number; accepted: {self}") from None
        if isinstance(value, float) and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text} is not accepted; accepted: {self}")
        if (self.low is not None and value < self.low) or (self.high is not None and value > self.high):
            raise argparse.ArgumentTypeError(f"{text} is out of range; accepted: {self}")
        return value
