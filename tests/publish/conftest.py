from __future__ import annotations

import copy
from pathlib import Path

import pytest

from tests.dataset.conftest import TINY, write_config

# A second version of TINY: one more frame per orbit (images added), stronger sun, a new version.
TINY_NEXT = copy.deepcopy(TINY)
TINY_NEXT["version"] = "0.1.0"
TINY_NEXT["camera"]["trajectories"][0]["frames"] = 3
TINY_NEXT["scene"] = {"lighting": {"sun": {"illuminance_lux": [90000.0, 120000.0]}}}

PUBLISHED_EPOCH = 1767225600  # 2026-01-01, for a reproducible card


@pytest.fixture(scope="session")
def source_dataset(tmp_path_factory) -> Path:
    """TINY built once with one worker and audited (its audit/ folder, which publish reads)."""
    from rebar_data.dataset.audit import audit_dataset
    from rebar_data.dataset.build import build_dataset

    root = tmp_path_factory.mktemp("pub-src")
    ds = build_dataset(write_config(root / "cfg"), root, workers=1)
    audit_dataset(ds)
    return ds


@pytest.fixture(scope="session")
def bundle(source_dataset, tmp_path_factory) -> Path:
    from rebar_data.publish.bundle import publish_dataset

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SOURCE_DATE_EPOCH", str(PUBLISHED_EPOCH))
        return publish_dataset(source_dataset, tmp_path_factory.mktemp("pub") / "bundle")


@pytest.fixture(scope="session")
def next_dataset(tmp_path_factory) -> Path:
    from rebar_data.dataset.build import build_dataset

    root = tmp_path_factory.mktemp("pub-next")
    return build_dataset(write_config(root / "cfg", TINY_NEXT), root, workers=1)
