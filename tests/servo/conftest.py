from __future__ import annotations

import pytest

from rebar_data.servo.config import SuiteConfig


def suite_dict(**over) -> dict:
    """A small suite on the fast ray-cast frames and the exact detector; keys in ``over`` replace the defaults."""
    base = {
        "name": "test",
        "seed": 3,
        "detector": "ground_truth",
        "frames": "raycast",
        "recording": {"rrd": "none"},
        "episodes": [
            {"mode": "ibvs", "start": {"look_at_m": [0.03, -0.02], "standoff_m": 0.6}, "targets": 1}
        ],
    }
    base.update(over)
    return base


@pytest.fixture(scope="session")
def servo_ctx(root):
    """A servo context (world, camera, ray-cast frames, exact detector) shared by the tests of a session."""
    import os

    from rebar_data.servo.run import build_context

    cwd = os.getcwd()
    os.chdir(root)
    try:
        ctx = build_context(SuiteConfig.model_validate(suite_dict()), root / "eval" / "ci.yaml")
    finally:
        os.chdir(cwd)
    yield ctx
    ctx.close()
