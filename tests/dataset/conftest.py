from __future__ import annotations

from pathlib import Path

import pytest
import yaml

TINY = {
    "name": "tiny",
    "version": "0.0.1",
    "seed": 5,
    "mesh": {"kind": "planar", "width_m": 0.8, "height_m": 0.6},
    "realism": {"tie_wire_fraction": 0.3, "jitter_m": 0.002},
    "camera": {
        "intrinsics": {"width": 160, "height": 120, "fx": 150.0, "fy": 150.0, "cx": 80.0, "cy": 60.0},
        "trajectories": [
            {"kind": "orbit_arc", "count": 3, "frames": 2, "edge_margin_m": 0.1},
            {"kind": "straight_pass", "count": 3, "frames": 2, "edge_margin_m": 0.1},
        ],
    },
}


def write_config(folder: Path, data: dict = TINY, name: str = "tiny.yaml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / name
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


@pytest.fixture(scope="session")
def tiny_config(tmp_path_factory) -> Path:
    return write_config(tmp_path_factory.mktemp("cfg"))


@pytest.fixture(scope="session")
def tiny_dataset(tiny_config, tmp_path_factory) -> Path:
    """The tiny dataset, built once with one worker; tests that change it work on a copy."""
    from rebar_data.dataset.build import build_dataset

    return build_dataset(tiny_config, tmp_path_factory.mktemp("ds"), workers=1)
