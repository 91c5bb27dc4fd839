"""What a long command has finished, kept in its output folder, so that the command run again after a kill (or
a power cut) picks up at the step it was in.

A :class:`Steps` record is one JSON file: each finished step's name, the key of what it was computed from (the
SHA-256 of its model files, its settings, the data it read) and its result. A step whose key is unchanged is
taken from the record; any other is computed again. The file is rewritten atomically after every step, so a
kill leaves the record of the steps before it."""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rebar_data.outputs import replace_file

STEPS_FILE = "steps.json"  # a run folder's record of its finished steps


def key_of(*parts: Any) -> str:
    """The SHA-256 of ``parts`` as sorted JSON: the key of what a step reads."""
    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _plain(value: Any) -> Any:
    """``value`` as JSON keeps it: NaN and infinities as strings, which :func:`_unplain` turns back."""
    if isinstance(value, float) and not math.isfinite(value):
        return {"__float__": repr(value)}
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def _unplain(value: Any) -> Any:
    if isinstance(value, dict):
        if set(value) == {"__float__"}:
            return float(value["__float__"])
        return {k: _unplain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_unplain(v) for v in value]
    return value


class Steps:
    """The record of a command's finished steps in ``path`` (created on the first step kept; None: kept in
    memory alone)."""

    def __init__(self, path: Path | None, *, log: Callable[[str], None] | None = None):
        self.path = None if path is None else Path(path)
        self.log = log
        self._done: dict[str, dict[str, Any]] = {}
        try:
            found = json.loads(self.path.read_text()) if self.path is not None else {}
        except (OSError, ValueError):
            found = {}  # none yet, or a damaged record: every step is computed again
        if isinstance(found, dict):
            self._done = {k: v for k, v in found.items() if isinstance(v, dict) and "key" in v}

    def done(self, name: str, key: str) -> bool:
        """Whether step ``name`` finished with the inputs ``key`` names."""
        return self._done.get(name, {}).get("key") == key

    def result(self, name: str) -> Any:
        return _unplain(self._done[name].get("result"))

    def keep(self, name: str, key: str, result: Any = None) -> None:
        """Record step ``name`` as finished on ``key`` with ``result`` (numbers, strings, lists, dicts)."""
        self._done[name] = {"key": key, "result": _plain(result)}
        if self.path is None:
            return
        text = json.dumps(self._done, indent=1, sort_keys=True, allow_nan=False) + "\n"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        replace_file(self.path, lambda tmp: tmp.write_text(text))

    def run(self, name: str, key: str, compute: Callable[[], Any]) -> Any:
        """Step ``name``'s result: the record's when it finished on ``key``, else ``compute()``'s, kept."""
        if self.done(name, key):
            self._say(f"{name}: done before, reused")
            return self.result(name)
        self._say(f"{name} ...")
        result = compute()
        self.keep(name, key, result)
        return result

    def _say(self, text: str) -> None:
        if self.log is not None:
            self.log(text)
