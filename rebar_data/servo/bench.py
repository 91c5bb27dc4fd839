"""Speed of the servo loop's parts, against the 32 ms control period measured in the same run.

``run()`` returns lines for ``rebar bench``: per control step, the physics (7-8 steps at 240 Hz), a
ray-cast frame, a rendered frame (when the renderer can start here), the exact detector, the tracker,
the IBVS control law with the model Jacobian and the PBVS numerical Jacobian calibration; then a whole
servo visit's cost per step.
"""

from __future__ import annotations

import time

import numpy as np

PERIOD_S = 0.032


def _per_call(fn, n: int) -> float:
    fn()
    t = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t) / n


def run() -> list[str]:
    from rebar_data.config import PAPER_PIPELINE
    from rebar_data.servo.config import EpisodeSpec, StartPose, SuiteConfig
    from rebar_data.servo.controllers import IbvsController, PbvsController
    from rebar_data.servo.episode import EpisodeRunner
    from rebar_data.servo.run import build_context
    from rebar_data.servo.tracker import TargetTracker

    suite = SuiteConfig.model_validate(
        {
            "name": "bench",
            "detector": "ground_truth",
            "frames": "raycast",
            "world": {"mesh_config": str(PAPER_PIPELINE)},
            "recording": {"rrd": "none"},
            "tcp": {"approach": False},
            "episodes": [
                {"mode": "ibvs", "start": {"look_at_m": [0.03, -0.02], "standoff_m": 0.6}, "targets": 1}
            ],
        }
    )
    ctx = build_context(suite)
    world, cam = ctx.world, ctx.camera
    start = StartPose(look_at_m=(0.03, -0.02), standoff_m=0.6)
    q, _ = world.solve_start(world.camera_pose_for(start))
    world.reset_joints(q)
    rng = np.random.default_rng(0)
    T = world.world_from_camera()
    lines = []

    def ms(x: float) -> str:
        return f"{x * 1000:.1f} ms ({x / PERIOD_S:.2f} of the 32 ms period)"

    physics = _per_call(world.step, 50)
    lines.append(f"servo physics per control step: {ms(physics)}")
    frame = ctx.frames.render(T, rng)
    raycast = _per_call(lambda: ctx.frames.render(T, rng), 10)
    lines.append(f"servo ray-cast frame 640x480: {ms(raycast)}")
    try:
        from rebar_data.servo.frames import RendererFrames

        rf = RendererFrames(ctx.rm, cam, np.random.default_rng(1), shadows=False)
        try:
            rendered = _per_call(lambda: rf.render(T, rng), 5)
        finally:
            rf.close()
        lines.append(
            f"servo rendered frame 640x480, no shadows: {ms(rendered)} = {rendered / raycast:.1f}x a ray-cast frame"
        )
    except Exception as e:  # no EGL here: report it rather than fail the whole bench
        lines.append(f"servo rendered frame: not measured ({type(e).__name__}: {e})")
    det = ctx.make_detector(rng)
    detect = _per_call(lambda: det.detect(frame.rgb), 20)
    lines.append(f"servo exact detector: {ms(detect)}")
    d = det.detect(frame.rgb)
    tr = TargetTracker()
    tr.seed(frame.rgb, d[0, :2])
    track = _per_call(lambda: tr.update(frame.rgb, d), 20)
    lines.append(f"servo tracker (KLT + update): {ms(track)}")
    ibvs = IbvsController(world, cam, suite.motion, suite.ibvs)
    ibvs.begin()
    law = _per_call(lambda: ibvs.joint_rates(ibvs.twist(d[0, :2], 0.6)[0]), 50)
    lines.append(f"servo IBVS law + model Jacobian: {ms(law)}")
    pbvs = PbvsController(world, cam, suite.motion, suite.pbvs)
    from rebar_data.servo.pbvs import calibrate_jacobian

    calib = _per_call(
        lambda: calibrate_jacobian(world.q, world.measure_camera_after, perturbation_rad=2e-3), 20
    )
    lines.append(f"servo PBVS Jacobian calibration (12 measured poses): {ms(calib)}")
    del pbvs
    spec = EpisodeSpec(mode="ibvs", start=start, targets=1)
    t0 = time.perf_counter()
    result = EpisodeRunner(ctx, spec, 0, np.random.SeedSequence(0)).run(start, q)
    wall = time.perf_counter() - t0
    steps = max(len(result.steps), 1)
    v = result.visits[0]
    lines.append(
        f"servo IBVS visit on ray-cast frames: {v.iterations} iterations, {wall / steps * 1000:.1f} ms a step "
        f"= {wall / steps / PERIOD_S:.1f}x slower than real time"
    )
    ctx.close()
    return lines


if __name__ == "__main__":
    print("\n".join(run()))
