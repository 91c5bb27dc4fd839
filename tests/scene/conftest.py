from __future__ import annotations

import pytest

from rebar_data.geometry.build import build_rebar_mesh
from rebar_data.geometry.config import MeshConfig

TUNNEL = {
    "seed": 3,
    "mesh": {
        "kind": "tunnel_segment",
        "intrados_arc_m": 0.78,
        "extrados_arc_m": 0.86,
        "width_m": 1.0,
        "thickness_m": 0.30,
    },
    "realism": {"tie_wire_fraction": 0.3},
}
PLANAR = {"seed": 4, "mesh": {"kind": "planar", "width_m": 0.8, "height_m": 0.6}}


@pytest.fixture(scope="session")
def tunnel_rm():
    return build_rebar_mesh(MeshConfig.model_validate(TUNNEL))


@pytest.fixture(scope="session")
def planar_rm():
    return build_rebar_mesh(MeshConfig.model_validate(PLANAR))
