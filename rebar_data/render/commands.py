"""`rebar render`: a few frames of a pipeline's scenes, to look at before building a dataset."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def run_render(args: argparse.Namespace) -> None:
    import cv2
    import numpy as np
    from tqdm import tqdm

    from rebar_data.dataset.config import load_pipeline
    from rebar_data.geometry.build import build_rebar_mesh
    from rebar_data.render.engines import check_engine, renderer_class
    from rebar_data.scene.cameras import intrinsics_from_config, trajectory_poses
    from rebar_data.scene.sample import sample_scene, sample_sensor

    cfg = load_pipeline(args.config)
    check_engine(cfg.render)
    rm = build_rebar_mesh(cfg.mesh_config())
    k = intrinsics_from_config(cfg.camera)
    rng = np.random.default_rng(cfg.seed if args.seed is None else args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    thumbs = []
    with renderer_class(cfg.render)(k, cfg.render) as renderer:
        renderer.set_mesh(rm)
        for i in tqdm(range(args.frames), desc="render", unit="frame", file=sys.stderr):
            renderer.set_scene(sample_scene(cfg.scene, rng))
            traj = cfg.camera.trajectories[i % len(cfg.camera.trajectories)]
            poses = trajectory_poses(traj, rm, rng)
            frame = renderer.render(poses[int(rng.integers(len(poses)))], sample_sensor(cfg.scene, rng), rng)
            bgr = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)
            cv2.imwrite(str(out / f"frame_{i:03d}_{traj.kind}.png"), bgr)
            thumbs.append(cv2.resize(bgr, (k.width // 2, k.height // 2), interpolation=cv2.INTER_AREA))
    cols = min(4, len(thumbs))
    rows = [thumbs[j : j + cols] for j in range(0, len(thumbs), cols)]
    rows[-1] += [np.zeros_like(thumbs[0])] * (cols - len(rows[-1]))
    cv2.imwrite(str(out / "contact_sheet.png"), np.vstack([np.hstack(r) for r in rows]))
    print(f"{len(thumbs)} frames, {k.width}x{k.height}, contact sheet contact_sheet.png", file=sys.stderr)
    print(out)


def register(sub: argparse._SubParsersAction) -> None:
    r = sub.add_parser("render", help="render a few frames of a pipeline's scenes to PNG, to look at")
    r.add_argument("config", help="pipeline YAML, such as pipelines/paper-tunnel.yaml")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--frames", type=int, default=8, help="frames, each a new scene (default 8)")
    r.add_argument("--seed", type=int, help="seed (default: the pipeline's)")
    r.set_defaults(func=run_render)
