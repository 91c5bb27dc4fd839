"""Run a servo suite end to end and write its outputs (the ``rebar servo run`` contract).

``DIR/episodes.parquet`` (one row per target visit), ``DIR/steps.parquet`` (one row per control step),
``DIR/summary.json``, ``DIR/report.md`` with its plots, and ``DIR/episode_<k>.rrd`` Rerun recordings.
Outputs are written to a temporary folder beside ``DIR`` and swapped into place at the end, so an
interrupted run never leaves a folder that looks finished. An existing ``DIR`` is replaced only when it is
an earlier run's (its mark, or summary.json and episodes.parquet); anything else there is refused.
"""

from __future__ import annotations

import json
import platform
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import rebar_data
from rebar_data.config import ConfigError
from rebar_data.outputs import OutputLock, mark_output, output_folder, remove_stale, replace_folder
from rebar_data.pipeline import load_pipeline
from rebar_data.render.raycast import Raycaster
from rebar_data.scene.sample import nominal_depth_sensor
from rebar_data.servo.alignment import CrossingTruth
from rebar_data.servo.camera import kinect_intrinsics
from rebar_data.servo.config import EpisodeSpec, StartPose, SuiteConfig, load_suite, resolve_path
from rebar_data.servo.context import ServoContext
from rebar_data.servo.detectors import GroundTruthDetector, load_shipped_detector
from rebar_data.servo.episode import EpisodeRunner
from rebar_data.servo.faults import faulty
from rebar_data.servo.frames import RaycastFrames, RendererFrames
from rebar_data.servo.recorder import Recorder
from rebar_data.servo.records import EpisodeResult
from rebar_data.servo.tour import CrossingMap, TourRunner, tour_summary
from rebar_data.servo.world import ServoWorld, build_world_mesh, check_reachable

RANDOM_EPISODE_OFFSET = 1000
TOUR_EPISODE_OFFSET = 2000
MAX_START_DRAWS = 50
COMMAND = "rebar servo run"


def check_run_out(out: str | Path) -> Path:
    """``out`` as a run may write it: new, empty, or an earlier run's folder (its inputs are files, which
    a folder never overwrites)."""
    return output_folder(out, arg="--out", command=COMMAND, swapped=True)


def build_context(suite: SuiteConfig, suite_path: str | Path | None = None) -> ServoContext:
    """World, camera, frame source and detector factory for a suite (a missing model fails first, fast)."""
    camera = kinect_intrinsics(suite.camera.fov_x_deg)
    shipped = (
        load_shipped_detector(
            suite.detector_path,
            camera,
            runtime=suite.detector_runtime,
            reading=suite.detector_reading,
            flatten_behind=suite.detector_flatten_behind,
        )
        if suite.detector == "shipped"
        else None
    )
    mesh_path = resolve_path(suite.world.mesh_config, suite_path)
    rm = build_world_mesh(suite.world, mesh_path)
    world = ServoWorld(suite.world, rm)
    root_seq = np.random.SeedSequence(suite.seed)
    scene_rng = np.random.default_rng(root_seq.spawn(1)[0])
    depth_sensor = nominal_depth_sensor(
        suite.camera.depth_sensor,
        suite.scene.depth_sensor,
        noise=suite.camera.depth_noise,
    )
    new_sensor = None
    if suite.frames == "renderer":
        try:
            frames = RendererFrames(
                rm,
                camera,
                scene_rng,
                shadows=suite.shadows,
                depth_sensor=depth_sensor,
                scene=suite.scene,
            )
        except BaseException:
            world.close()
            raise
        new_sensor = frames.new_sensor
    else:
        frames = RaycastFrames(rm, camera, Raycaster(rm), depth_sensor=depth_sensor)
    base = shipped or GroundTruthDetector(rm, camera, frames.cast_rays, world.world_from_camera)

    def make_detector(rng: np.random.Generator):
        return faulty(base, suite, rng, camera)

    bar_diameter_m = max(b.diameter_m for b in rm.bars)
    return ServoContext(
        suite=suite,
        world=world,
        rm=rm,
        camera=camera,
        frames=frames,
        make_detector=make_detector,
        depth_offset_m=float(bar_diameter_m),
        detector_name=suite.detector,
        truth=CrossingTruth.of(rm),
        new_sensor=new_sensor,
    )


def plan_episodes(
    suite: SuiteConfig, ctx: ServoContext
) -> list[tuple[int, EpisodeSpec, StartPose, np.ndarray]]:
    """Every episode with its start pose and start joints: listed ones first, then the random ones.

    Random start poses are drawn from the suite's ranges with the episode's own generator and redrawn
    (up to 50 times) until the arm can reach them.
    """
    plan = []
    for i, spec in enumerate(suite.episodes):
        q = check_reachable(ctx.world, spec.start, f"episodes[{i}].start")
        plan.append((i, spec, spec.start, q))
    r = suite.random
    if r is not None:
        for j in range(r.count):
            index = RANDOM_EPISODE_OFFSET + j
            rng = np.random.default_rng(np.random.SeedSequence([suite.seed, index]))
            spec = EpisodeSpec(mode=r.modes[j % len(r.modes)], targets=r.targets, choice=r.choice)
            for _ in range(MAX_START_DRAWS):
                start = StartPose(
                    look_at_m=(float(rng.uniform(*r.axial_m)), float(rng.uniform(*r.arc_m))),
                    standoff_m=float(rng.uniform(*r.standoff_m)),
                    tilt_deg=(
                        float(rng.uniform(-r.tilt_deg, r.tilt_deg)),
                        float(rng.uniform(-r.tilt_deg, r.tilt_deg)),
                    ),
                    roll_deg=float(rng.uniform(-r.roll_deg, r.roll_deg)),
                )
                q, ok = ctx.world.solve_start(ctx.world.camera_pose_for(start))
                if ok:
                    break
            else:
                raise ConfigError(
                    f"random: no reachable start pose in {MAX_START_DRAWS} draws for episode {j}; accepted: "
                    "narrower axial_m / arc_m / standoff_m ranges"
                )
            plan.append((index, spec.model_copy(update={"start": start}), start, q))
    return plan


def plan_tour(suite: SuiteConfig, ctx: ServoContext) -> list[tuple[int, np.ndarray, StartPose, np.ndarray]]:
    """Each tour base as (episode index, base offset, start pose, start joints); one the arm cannot reach
    from its base is a ConfigError naming it."""
    tour = suite.tour
    if tour is None:
        return []
    world = ctx.world
    crown, _ = world.surface_point(0.0, 0.0)
    plan = []
    try:
        for i, b in enumerate(tour.bases):
            offset = world.surface_point(b.axial_m, b.arc_m)[0] - crown
            world.move_base(offset)
            start = StartPose(look_at_m=(b.axial_m, b.arc_m), standoff_m=tour.standoff_m)
            q, ok = world.solve_start(world.camera_pose_for(start))
            if not ok:
                raise ConfigError(
                    f"tour.bases[{i}]: the arm on that base cannot look at ({b.axial_m}, {b.arc_m}) from "
                    f"{tour.standoff_m} m; accepted: a base whose look-at point is on the element and a standoff_m "
                    "of 0.5-0.7 m"
                )
            plan.append((TOUR_EPISODE_OFFSET + i, offset, start, q))
    finally:
        world.move_base(np.zeros(3))
    return plan


def run_suite(
    suite_path: str | Path,
    out: str | Path,
    *,
    recorder_factory=None,
    progress: bool = True,
    limit_episodes: int | None = None,
) -> dict:
    """Run every episode of a suite and write the outputs to ``out``; returns the summary.

    ``out`` is replaced only when it is an earlier run's folder (see :func:`check_run_out`); ``limit_episodes``
    runs the first episodes only (1 or more).
    """
    if limit_episodes is not None and limit_episodes < 1:
        raise ConfigError(f"--episodes {limit_episodes}: runs nothing; accepted: an integer >= 1")
    out = check_run_out(out)
    suite = load_suite(suite_path)
    if not suite.episodes and suite.random is None and suite.tour is None:
        raise ConfigError(
            f"{suite_path}: has only a map section, which `{COMMAND}` does not run; accepted: rebar servo map "
            f"{suite_path} --out DIR, or a suite with episodes, random or tour"
        )
    # the pipeline the world's mesh comes from is checked whole before anything is written
    load_pipeline(resolve_path(suite.world.mesh_config, suite_path))
    t0 = time.perf_counter()
    ctx = build_context(suite, suite_path)
    try:
        summary = _run_episodes(suite, ctx, out, t0, recorder_factory, progress, limit_episodes)
    finally:
        ctx.close()  # the renderer is one per process: never leave it open
    return summary


def _run_episodes(suite, ctx, out: Path, t0: float, recorder_factory, progress: bool, limit_episodes) -> dict:
    plan = plan_episodes(suite, ctx)
    if limit_episodes is not None:
        plan = plan[:limit_episodes]
    # only now, with the model loaded and every start pose reachable, does the run write anything
    with OutputLock(out, command=COMMAND):
        check_run_out(out)  # again under the lock: another writer may have finished there meanwhile
        remove_stale(out.parent, f".{out.name}.tmp-*")  # a killed run's (the lock proves it dead)
        return _write_run(suite, ctx, plan, out, t0, recorder_factory, progress)


def _write_run(suite, ctx, plan, out: Path, t0: float, recorder_factory, progress: bool) -> dict:
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.tmp-") as tmp:
        tmpdir = Path(tmp) / "run"
        tmpdir.mkdir()
        if recorder_factory is None:
            from rebar_data.servo.recording import recorder_for

            def recorder_factory(k, index, spec, ctx=ctx, tmpdir=tmpdir):
                return recorder_for(suite, ctx, tmpdir, k, index, spec)

        results: list[EpisodeResult] = []
        tour_plan = plan_tour(suite, ctx)
        bar = _progress(len(plan) + len(tour_plan), progress)
        snap_modes: set[str] = set()
        crossing_map = None
        if suite.tour is not None:
            crossing_map = CrossingMap(suite.tour.merge_radius_m)
            ties_left = suite.tour.max_ties
            for j, (index, offset, start, q) in enumerate(tour_plan):
                rec = recorder_factory(len(plan) + j, index, EpisodeSpec(mode=suite.tour.mode)) or Recorder()
                seq = np.random.SeedSequence([suite.seed, index, 7])
                ctx.world.move_base(offset)
                runner = TourRunner(
                    ctx, suite.tour, index, seq, rec, crossing_map=crossing_map, ties_left=ties_left
                )
                try:
                    runner.run_base(start, q)
                finally:
                    rec.close()
                    ctx.world.move_base(np.zeros(3))
                ties_left = runner.ties_left
                results.append(runner.result)
                bar(len(plan) + j, results[-1])
                if ties_left is not None and ties_left <= 0:
                    break
        for k, (index, spec, start, q) in enumerate(plan):
            rec = recorder_factory(k, index, spec) or Recorder()
            seq = np.random.SeedSequence([suite.seed, index, 7])
            runner = EpisodeRunner(ctx, spec, index, seq, rec, snapshots=spec.mode not in snap_modes)
            snap_modes.add(spec.mode)
            try:
                results.append(runner.run(start, q))
            finally:
                rec.close()
            bar(k, results[-1])
        summary = write_outputs(
            suite, ctx, results, tmpdir, wall_s=time.perf_counter() - t0, crossing_map=crossing_map
        )
        mark_output(tmpdir, COMMAND)
        replace_folder(tmpdir, out)
    return summary


def _progress(total: int, enabled: bool):
    def show(k: int, result: EpisodeResult) -> None:
        if not enabled:
            return
        ok = sum(v.converged for v in result.visits)
        print(
            f"episode {k + 1}/{total}: {result.visits[0].mode if result.visits else '?'}, "
            f"{ok}/{len(result.visits)} visits converged",
            file=sys.stderr,
            flush=True,
        )

    return show


def write_outputs(
    suite: SuiteConfig,
    ctx: ServoContext,
    results: list[EpisodeResult],
    out: Path,
    *,
    wall_s: float,
    crossing_map: CrossingMap | None = None,
) -> dict:
    from rebar_data.servo.report import summarize, write_report

    visits = [v.to_dict() for r in results for v in r.visits]
    steps = [asdict(s) for r in results for s in r.steps]
    pq.write_table(pa.Table.from_pylist(visits), out / "episodes.parquet")
    pq.write_table(pa.Table.from_pylist(steps) if steps else pa.table({}), out / "steps.parquet")
    summary = summarize(visits)
    if crossing_map is not None:
        summary["tour"] = tour_summary(visits, steps, crossing_map, len(ctx.rm.crossings))
    summary.update(
        {
            "suite": suite.name,
            "seed": suite.seed,
            "detector": suite.detector,
            "frames": suite.frames,
            "faults": suite.faults.model_dump(),
            "camera": {**asdict(ctx.camera), "fov_deg": ctx.camera.fov_deg},
            "config": suite.model_dump(mode="json"),
            "wall_s": wall_s,
            "python": platform.python_version(),
            "package_version": rebar_data.__version__,
        }
    )
    (out / "summary.json").write_text(
        json.dumps(summary, indent=2, sort_keys=True, default=json_default) + "\n"
    )
    snapshots: dict[str, list] = {}
    for r in results:
        if r.snapshots and r.visits:
            snapshots.setdefault(r.visits[0].mode, r.snapshots)
    write_report(suite, visits, steps, out, summary, snapshots)
    return summary


def json_default(x):
    """``json.dumps``' ``default`` for the numbers and arrays of a run's summary."""
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")
