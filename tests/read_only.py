"""A fixture for read-only folders that also holds as root, who may write anywhere."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


@pytest.fixture(name="read_only")
def read_only_fixture(monkeypatch):
    """Make a read-only folder; as root the process is also told it may not write there (``os.access``),
    which is what the commands ask before they write."""
    made: list[Path] = []
    real = os.access

    def access(path, mode, *args, **kwargs):
        if mode & os.W_OK and Path(path).absolute() in made:
            return False
        return real(path, mode, *args, **kwargs)

    if os.geteuid() == 0:
        monkeypatch.setattr(os, "access", access)

    def make(path: Path) -> Path:
        path.mkdir(exist_ok=True)
        path.chmod(0o555)
        made.append(path.absolute())
        return path

    yield make
    for p in made:
        p.chmod(0o755)
