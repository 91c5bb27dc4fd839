"""Episode logic on the fast frames: tracking between detector calls, reproducibility, a lost target, divergence."""

from __future__ import annotations

import dataclasses

import numpy as np

from rebar_data.servo.config import EpisodeSpec, StartPose, SuiteConfig
from rebar_data.servo.controllers import IbvsController
from rebar_data.servo.episode import EpisodeRunner

from .conftest import suite_dict


class _Blinded:
    """The exact detector, blind (no detections) on frames ``first`` to ``last`` of the episode."""

    dropped = False

    def __init__(self, inner, first: int, last: int):
        self.inner, self.first, self.last, self.calls = inner, first, last, 0

    def detect(self, rgb, *, depth=None):
        self.calls += 1
        out = self.inner.detect(rgb, depth=depth)
        return out[:0] if self.first <= self.calls <= self.last else out


def _run(ctx, mode="ibvs", *, make_detector=None, tcp=False, **over):
    suite = SuiteConfig.model_validate(suite_dict(tcp={"approach": tcp}, **over))
    c = dataclasses.replace(ctx, suite=suite, make_detector=make_detector or ctx.make_detector)
    start = StartPose(look_at_m=(0.03, -0.02), standoff_m=0.6)
    q, ok = c.world.solve_start(c.world.camera_pose_for(start))
    assert ok
    spec = EpisodeSpec(mode=mode, start=start, targets=1)
    return EpisodeRunner(c, spec, 0, np.random.SeedSequence(1)).run(start, q)


def test_klt_carries_the_target_between_detector_calls(servo_ctx):
    r = _run(servo_ctx, tracker={"detect_every": 4})
    sources = [s.tracker for s in r.steps if s.phase == "servo"]
    assert "predicted" in sources and "detected" in sources
    assert r.visits[0].converged and r.visits[0].final_true_lateral_error_m < 0.001


def test_an_episode_is_reproducible(servo_ctx):
    a, b = _run(servo_ctx), _run(servo_ctx)
    assert len(a.steps) == len(b.steps)
    np.testing.assert_allclose([s.q for s in a.steps], [s.q for s in b.steps], atol=1e-9)
    assert a.visits[0].iterations == b.visits[0].iterations


def test_a_lost_target_holds_still_then_is_reacquired(servo_ctx):
    r = _run(servo_ctx, make_detector=lambda rng: _Blinded(servo_ctx.make_detector(rng), 8, 24))
    (v,) = r.visits
    held = [s for s in r.steps if s.phase == "servo" and np.isnan(s.depth_m)]
    assert len(held) >= 5  # it stopped while blind...
    assert all(np.allclose(s.twist, 0) for s in held)
    assert v.converged  # ...and finished the visit once it saw the target again


def test_a_target_never_seen_again_ends_the_visit_as_lost(servo_ctx):
    r = _run(servo_ctx, make_detector=lambda rng: _Blinded(servo_ctx.make_detector(rng), 6, 10**6))
    assert r.visits[0].reason == "lost"


def test_a_diverging_controller_is_stopped(servo_ctx, monkeypatch):
    real = IbvsController.twist

    def wrong_sign(self, uv, Z, omega=None):
        twist, err_px, err_m = real(self, uv, Z, omega)
        return -twist, err_px, err_m

    monkeypatch.setattr(IbvsController, "twist", wrong_sign)
    r = _run(servo_ctx)
    assert r.visits[0].reason == "diverged"
    assert not r.visits[0].converged
