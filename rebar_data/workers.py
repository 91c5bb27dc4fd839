"""Local worker processes for commands that spread independent work over cores (``rebar dataset build``,
``rebar servo map``).

Workers are started with ``spawn``, never ``fork``: a process forked after EGL and Filament were initialised
in the parent can hang. They start with Ctrl-C ignored (:func:`sigint_ignored`, inherited): the terminal sends
it to every process of the group, and the parent alone answers it, ending its workers when it stops.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from rebar_data.config import ConfigError


@contextmanager
def sigint_ignored() -> Iterator[None]:
    """Ctrl-C ignored for the block (in the main thread), so that processes started in it inherit that."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def check_workers(workers: int | None, *, backend: str = "local") -> None:
    """``--workers`` within bounds: 1 to the machine's cores for local processes, 1 or more Ray actors."""
    if workers is None:
        return
    if backend == "ray":
        if workers < 1:
            raise ConfigError(f"--workers {workers}: not a number of Ray actors; accepted: 1 or more")
        return
    cores = os.cpu_count() or 1
    if not 1 <= workers <= cores:
        raise ConfigError(
            f"--workers {workers}: out of range; accepted: 1 to {cores} (this machine's cores; one worker "
            "already keeps two cores busy)"
        )
