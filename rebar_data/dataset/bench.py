"""End-to-end dataset throughput (render + label + write) with one worker, all cores, and on Ray.

Builds a slice of ``pipelines/paper-tunnel.yaml`` (the paper's mesh, 640x640, shadows as configured:
3 scenes x 3 trajectories x 16 frames = 144 images) three times in a temporary folder (the third on a
local Ray cluster when Ray is installed); the one-worker build is the same-run reference for the
speed-up. Start-up (spawning workers, building the mesh, the first shadowed frame) is included, so a
slice this size reads a little below a full build's rate.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import yaml

from rebar_data.config import PAPER_PIPELINE, read_yaml
from rebar_data.dataset.build import build_dataset


def bench_config(tmp: Path, *, scenes: int = 3, frames: int = 16) -> Path:
    data = read_yaml(PAPER_PIPELINE)
    trajectories = data.get("camera", {}).get("trajectories") or [
        {"kind": "orbit_arc"},
        {"kind": "straight_pass"},
        {"kind": "approach"},
    ]
    data.setdefault("camera", {})["trajectories"] = [
        {**t, "count": scenes, "frames": frames} for t in trajectories
    ]
    data["name"] = "bench"
    p = tmp / "bench.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def run() -> list[str]:
    cores = os.cpu_count() or 1
    lines = []
    with tempfile.TemporaryDirectory() as tmp:
        cfg = bench_config(Path(tmp))
        rates = {}
        for workers in sorted({1, cores}):
            t = time.perf_counter()
            ds = build_dataset(cfg, Path(tmp) / f"w{workers}", workers=workers)
            dt = time.perf_counter() - t
            n = len(list((ds / "images").rglob("*.png")))
            rates[workers] = n / dt
            lines.append(
                f"dataset build, {workers} worker(s): {n} images 640x640 in {dt:.1f} s = {n / dt:.2f} img/s end to end"
            )
        if cores > 1:
            lines.append(
                f"speed-up {cores} workers over 1: {rates[cores] / rates[1]:.2f}x; "
                f"paper dataset (1200 images) would take {1200 / rates[cores] / 60:.1f} min (goal: >= 3 img/s, < 7 min)"
            )
        lines += _ray_lines(cfg, Path(tmp), cores, rates[cores])
        lines += _breakdown_lines(cfg, Path(tmp))
    return lines


# the stages of a frame in a build worker, in order; "render" holds the renderer's own three
FRAME_STAGES = ("scene", "render", "depth_sensor", "labels", "png", "write")
RENDER_STAGES = ("filament", "rays", "sensor")


def _breakdown_lines(cfg_path: Path, tmp: Path, *, trajectories: int = 3) -> list[str]:
    """Where a frame's time goes in one build worker process (one core, as in a build with a worker a
    core): its stages' seconds a frame, measured after the worker has rendered one trajectory."""
    import multiprocessing as mp

    from rebar_data.dataset.build import prepare_staging
    from rebar_data.dataset.plan import make_plan
    from rebar_data.dataset.worker import init_process, run_in_process, stage_seconds_in_process
    from rebar_data.geometry.build import build_rebar_mesh
    from rebar_data.pipeline import load_pipeline

    cfg = load_pipeline(cfg_path)
    rm = build_rebar_mesh(cfg.mesh_config())
    plan = make_plan(cfg, rm)
    staging = prepare_staging(cfg, tmp / "breakdown", force=True, resume=False)
    tasks = [
        (t.trajectory_id, plan.scenes[t.scene_index], plan.samples_of(t.trajectory_id))
        for t in plan.trajectories[: trajectories + 1]
    ]
    with mp.get_context("spawn").Pool(1, initializer=init_process, initargs=(cfg, staging, None)) as pool:
        pool.apply(run_in_process, (tasks[0],))  # warm: first shadowed frame, texture cache
        before = pool.apply(stage_seconds_in_process)
        frames = sum(len(pool.apply(run_in_process, (t,))[1]) for t in tasks[1:])
        after = pool.apply(stage_seconds_in_process)

    def per_frame(group: str, stage: str) -> float:
        return (after[group].get(stage, (0.0, 0))[0] - before[group].get(stage, (0.0, 0))[0]) / frames

    render = {k: per_frame("render", k) for k in RENDER_STAGES}
    frame = {k: per_frame("frame", k) for k in FRAME_STAGES}
    total = sum(frame.values())
    other = frame["render"] - sum(render.values())
    parts = [f"Filament render {render['filament'] * 1000:.0f} ms ({render['filament'] / total:.0%})"]
    parts += [
        f"depth/instance rays {render['rays'] * 1000:.0f} ms",
        f"sensor effects {render['sensor'] * 1000:.0f} ms",
    ]
    parts += [
        f"depth sensor {frame['depth_sensor'] * 1000:.0f} ms "
        f"({frame['depth_sensor'] / max(render['filament'], 1e-9):.0%} of the Filament render)",
        f"labels {frame['labels'] * 1000:.0f} ms",
        f"PNG encoding {frame['png'] * 1000:.0f} ms",
    ]
    parts += [f"file writes {frame['write'] * 1000:.0f} ms", f"scene changes {frame['scene'] * 1000:.0f} ms"]
    if other > 0.0005:
        parts.append(f"rest {other * 1000:.0f} ms")
    return [
        f"a frame in one build worker (one core, {frames} frames): {total * 1000:.0f} ms = "
        + " + ".join(parts),
        f"  -> {1 / total:.2f} img/s a worker; the render (Filament, rays, sensor) is "
        f"{frame['render'] / total:.0%} of a frame",
    ]


def _ray_lines(cfg: Path, tmp: Path, cores: int, local_rate: float) -> list[str]:
    """The same build on a local Ray cluster with one actor per core, against the local backend's rate."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return ["ray backend: skipped (pip install -e '.[ray]')"]
    from rebar_data.dataset.ray_backend import build_dataset_ray

    t = time.perf_counter()
    ds = build_dataset_ray(cfg, tmp / "ray", actors=cores)
    dt = time.perf_counter() - t
    n = len(list((ds / "images").rglob("*.png")))
    return [
        f"dataset build, ray backend, {cores} actors (local cluster, start included): {n} images in {dt:.1f} s "
        f"= {n / dt:.2f} img/s; {n / dt / local_rate:.2f}x the local backend with {cores} workers"
    ]
