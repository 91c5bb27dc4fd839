"""Local worker processes for the commands that spread independent work over this machine's cores
(``dataset build --workers``, ``servo map --workers``).

Spawn, not fork: a process forked after EGL and Filament were initialised in the parent can hang. Workers
ignore Ctrl-C from their start (inherited) and in their initializer (:func:`worker_setup`): the terminal
sends it to every process of the group, and the parent alone answers it, ending the workers (terminate)
when it stops.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import threading
from collections.abc import Callable, Iterable, Iterator
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


def worker_setup() -> None:
    """A worker process's first step: Ctrl-C ignored, the offscreen renderer's platform, and one rasteriser
    thread (the workers already use every core, and Mesa's llvmpipe would otherwise start a thread per core
    in each of them)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ.setdefault("EGL_PLATFORM", "surfaceless")
    os.environ.setdefault("LP_NUM_THREADS", "1")


def pool_map(
    processes: int, initializer: Callable, initargs: tuple, run: Callable, tasks: Iterable
) -> Iterator[object]:
    """``run`` over ``tasks`` on a spawn pool of ``processes`` workers, each set up by ``initializer``;
    results in the order they finish. The workers end with the iteration, however it ends."""
    with sigint_ignored():
        pool = mp.get_context("spawn").Pool(processes, initializer=initializer, initargs=initargs)
    try:
        yield from pool.imap_unordered(run, tasks)
    finally:
        pool.terminate()
        pool.join()
