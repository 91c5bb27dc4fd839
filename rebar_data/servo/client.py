"""One pybullet connection, wrapped so that every call names its client (no global simulator state)."""

from __future__ import annotations

import contextlib
import functools
import os
from typing import Any


@contextlib.contextmanager
def quiet_stdout():
    """Silence C-level stdout and stderr (pybullet prints its build time and URDF warnings there)."""
    try:
        saved = [os.dup(1), os.dup(2)]
    except OSError:
        yield
        return
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
            yield
            _flush_c_stdout()  # C's stdio buffers: flush them while they still go to /dev/null
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])


def _flush_c_stdout() -> None:
    try:
        import ctypes

        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):
        pass


with quiet_stdout():
    import pybullet


class BulletClient:
    """A DIRECT-mode pybullet connection whose methods pass ``physicsClientId`` on every call.

    ``client.loadURDF(...)`` is ``pybullet.loadURDF(..., physicsClientId=client.id)``; constants
    (``client.GEOM_BOX``) are read through unchanged. Several clients can live in one process.
    """

    def __init__(self) -> None:
        with quiet_stdout():
            self.id = pybullet.connect(pybullet.DIRECT)
        if self.id < 0:
            raise RuntimeError("pybullet could not open a DIRECT connection")

    def __getattr__(self, name: str) -> Any:
        attr = getattr(pybullet, name)
        if callable(attr) and not isinstance(attr, type):
            return functools.partial(attr, physicsClientId=self.id)
        return attr

    def close(self) -> None:
        """Disconnect; safe to call twice."""
        if self.id >= 0:
            pybullet.disconnect(physicsClientId=self.id)
            self.id = -1

    def __enter__(self) -> BulletClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # interpreter shutdown: pybullet may be gone already
            self.close()
