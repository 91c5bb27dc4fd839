from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("EGL_PLATFORM", "surfaceless")

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def root() -> Path:
    return ROOT


@pytest.fixture
def write_yaml(tmp_path):
    """Write a YAML config from a dict and return its path."""
    import yaml

    def _write(data: dict, name: str = "cfg.yaml") -> Path:
        p = tmp_path / name
        p.write_text(yaml.safe_dump(data, sort_keys=False))
        return p

    return _write
