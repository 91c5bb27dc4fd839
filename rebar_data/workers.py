"""Local worker processes for commands that spread independent work over cores (``rebar dataset build``,
``rebar servo map``).

Workers are started with ``spawn``, never ``fork``: a process forked after EGL and Filament were initialised
in the parent can hang. They start with Ctrl-C ignored (:func:`sigint_ignored`, inherited): the terminal sends
it to every process of the group, and the parent alone answers it, ending its workers when it stops.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


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
