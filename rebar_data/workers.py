"""Local worker processes for commands that spread independent work over cores (``rebar dataset build``,
``rebar servo map``).

Workers are started with ``spawn``, never ``fork``: a process forked after EGL and Filament were initialised
in the parent can hang. They start with Ctrl-C ignored (:func:`sigint_ignored`, inherited): the terminal sends
it to every process of the group, and the parent alone answers it, ending its workers when it stops.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

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


def renderer_process(*, answers_ctrl_c: bool = False) -> None:
    """Set up a process that runs one renderer among others: EGL without a display, one llvmpipe rasteriser
    thread (the processes already use every core, and Mesa would otherwise start a thread per core in each),
    and, unless it ``answers_ctrl_c`` (a Ray actor, which Ray ends), Ctrl-C ignored: its parent ends it."""
    os.environ.setdefault("EGL_PLATFORM", "surfaceless")
    os.environ.setdefault("LP_NUM_THREADS", "1")
    if not answers_ctrl_c:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def spawned_pool_map(
    processes: int, initializer: Callable[..., None], initargs: tuple, fn: Callable[[Any], Any], tasks: list
) -> Iterator[Any]:
    """``fn`` over ``tasks`` on a spawned pool of ``processes`` (each set up by ``initializer(*initargs)``),
    results as they finish; the pool is ended when the caller stops reading (Ctrl-C, an error, done)."""
    ctx = mp.get_context("spawn")
    with sigint_ignored():
        pool = ctx.Pool(processes, initializer=initializer, initargs=initargs)
    try:
        yield from pool.imap_unordered(fn, tasks, chunksize=1)
    finally:
        pool.terminate()
        pool.join()
