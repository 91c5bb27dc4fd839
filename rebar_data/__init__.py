"""rebar-servo: synthetic rebar datasets, an intersection detector, and visual servoing evaluation."""

from __future__ import annotations

__version__ = "0.2.0"
