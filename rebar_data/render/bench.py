"""Renderer speed and memory: `rebar bench` prints these lines.

One renderer at 640x640 on the paper's tunnel mesh: seconds a frame split into the Filament render, the
ray cast for depth and instance ids, and the sensor effects, with and without shadows; each depth sensor
model's time on the frames' exact depth, as a share of the frame with shadows; the cost of a
scene change; RSS before and after a run of frames (it should stay flat); and, as the reference
measured in the same run, a plain render of the same mesh (one light, untextured, no shadows, no rays),
the set-up the project's design notes timed at 0.12 s. The goal is 3 images/s end to end with two
worker processes on two cores, so about 0.67 s a frame per worker.
"""

from __future__ import annotations

import resource
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

GOAL_IMAGES_PER_S = 3.0
WORKERS = 2
BENCH_FRAMES = 24


def _rss_mb() -> float:
    """Current resident set size (MB), from /proc when there is one."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _paper_mesh():
    from rebar_data.config import PAPER_PIPELINE
    from rebar_data.geometry.build import build_rebar_mesh
    from rebar_data.pipeline import load_mesh_config

    return build_rebar_mesh(load_mesh_config(PAPER_PIPELINE))


def _frames(renderer, poses, sensors, rng) -> np.ndarray:
    """Seconds per frame: (render, rays, sensor) rows."""
    from rebar_data.render.sensor import apply_sensor

    k = renderer.intrinsics
    out = []
    for T, s in zip(poses, sensors, strict=True):
        t0 = time.perf_counter()
        raw = renderer.render_raw(T)
        t1 = time.perf_counter()
        renderer.depth_and_instance(T)
        t2 = time.perf_counter()
        apply_sensor(raw, s, rng, principal_point=(k.cx, k.cy))
        out.append((t1 - t0, t2 - t1, time.perf_counter() - t2))
    return np.array(out)


def _plain_reference(rm, intrinsics, poses) -> float:
    """Seconds per frame of a bare render: merged mesh, one grey material, one sun, no shadows."""
    import open3d as o3d

    from rebar_data.render.renderer import _offscreen

    ren = _offscreen(intrinsics.width, intrinsics.height)
    scene = ren.scene
    scene.clear_geometry()
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(rm.mesh.vertices)), o3d.utility.Vector3iVector(rm.mesh.faces)
    )
    mesh.compute_vertex_normals()
    mat = o3d.visualization.rendering.MaterialRecord()
    mat.shader = "defaultLit"
    scene.add_geometry("plain", mesh, mat)
    scene.scene.add_directional_light("plain_sun", [1.0, 1.0, 1.0], [0.2, 0.3, -1.0], 80000.0, False)
    scene.view.set_shadowing(False)
    times = []
    for T in poses:
        ren.setup_camera(intrinsics.K, np.linalg.inv(T), intrinsics.width, intrinsics.height)
        t0 = time.perf_counter()
        ren.render_to_image()
        times.append(time.perf_counter() - t0)
    scene.clear_geometry()
    scene.scene.remove_light("plain_sun")
    return float(np.median(times[2:]))


def depth_sensor_lines(depths: list[np.ndarray], fx: float, frame_s: float, *, repeats: int = 3) -> list[str]:
    """Each depth sensor model's time a frame on these exact depth images (median over frames and repeats),
    against ``frame_s`` (a rendered frame's time measured in the same run), and the share of the pixels with
    a surface it measures."""
    from dataclasses import replace as with_changes

    from rebar_data.render.depth_sensor import sense_depth
    from rebar_data.scene.config import DEPTH_MODELS
    from rebar_data.scene.sample import nominal_depth_sensor

    h, w = depths[0].shape
    parts = []
    for model in DEPTH_MODELS:
        s = with_changes(nominal_depth_sensor(model), shift_x_px=1.0)  # misregistration included
        rng = np.random.default_rng(0)
        times, shares = [], []
        for z in depths:
            for _ in range(repeats):
                t0 = time.perf_counter()
                out = sense_depth(z, s, rng, fx=fx)
                times.append(time.perf_counter() - t0)
            shares.append(float((out[z > 0] > 0).mean()))
        t = float(np.median(times))
        parts.append(f"{model} {t * 1000:.1f} ms ({t / frame_s:.1%}, {np.mean(shares):.0%} measured)")
    return [f"  depth sensor a {w}x{h} frame, against the frame with shadows: " + "; ".join(parts)]


def run() -> list[str]:
    from rebar_data.render.renderer import Renderer
    from rebar_data.scene.cameras import PRESETS, trajectory_poses
    from rebar_data.scene.config import CameraConfig, RenderConfig, SceneConfig
    from rebar_data.scene.sample import sample_scene, sample_sensor

    rm = _paper_mesh()
    k = PRESETS["square_640"]
    rng = np.random.default_rng(0)
    cam = CameraConfig()
    poses = np.concatenate(
        [trajectory_poses(t, rm, rng)[:: max(1, t.frames // 8)][:8] for t in cam.trajectories]
    )
    poses = np.concatenate([poses, poses])[:BENCH_FRAMES]
    scene_cfg = SceneConfig()
    sensors = [sample_sensor(scene_cfg, rng) for _ in poses]
    scenes = [sample_scene(scene_cfg, np.random.default_rng(s)) for s in range(3)]
    lines = [
        f"render: paper-tunnel mesh ({len(rm.mesh.faces)} triangles), {k.width}x{k.height}, one renderer"
    ]
    with tempfile.TemporaryDirectory() as cache:
        t0 = time.perf_counter()
        renderer = Renderer(k, RenderConfig(cache_dir=Path(cache)))
        renderer.set_mesh(rm)
        start_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        renderer.set_scene(replace(scenes[0], shadows=True))
        cold_s = time.perf_counter() - t0
        warm = []
        for s in scenes[1:]:
            t0 = time.perf_counter()
            renderer.set_scene(replace(s, shadows=True))
            warm.append(time.perf_counter() - t0)
        lines.append(
            f"  start {start_s:.2f} s; scene change {np.mean(warm):.2f} s ({cold_s:.2f} s with a cold texture cache)"
        )
        _frames(renderer, poses[:3], sensors[:3], rng)  # warm up
        rss0 = _rss_mb()
        results = {}
        for label, shadows in (("with shadows", True), ("without shadows", False)):
            renderer.set_scene(replace(scenes[-1], shadows=shadows))
            results[label] = _frames(renderer, poses, sensors, rng)
        rss1 = _rss_mb()
        depths = [renderer.depth_and_instance(pose)[0] for pose in poses[:8]]
        renderer.close()
    plain = _plain_reference(rm, k, poses[:10])
    budget = WORKERS / GOAL_IMAGES_PER_S
    for label, t in results.items():
        med = np.median(t, axis=0)
        total = float(med.sum())
        lines.append(
            f"  {label:16s} {total:.3f} s/frame = render {med[0]:.3f} + depth/instance rays {med[1]:.3f}"
            f" + sensor {med[2]:.3f} -> {1 / total:.2f} images/s ({total / plain:.1f}x the plain render)"
        )
    shadow_total = float(np.median(results["with shadows"], axis=0).sum())
    lines.append(
        f"  reference: plain render (one light, untextured, no shadows, no rays) {plain:.3f} s/frame"
    )
    lines.append(
        f"  memory: RSS {rss0:.0f} MB before and {rss1:.0f} MB after {2 * len(poses)} frames "
        f"({rss1 - rss0:+.0f} MB)"
    )
    lines += depth_sensor_lines(depths, k.fx, shadow_total)
    verdict = "meets" if shadow_total <= budget else "misses"
    lines.append(
        f"  goal {GOAL_IMAGES_PER_S:g} images/s with {WORKERS} workers needs <= {budget:.2f} s/frame per worker: "
        f"{verdict} it with shadows ({shadow_total / budget:.2f}x the budget, if the workers get a core each)"
    )
    return lines


if __name__ == "__main__":
    print("\n".join(run()))
