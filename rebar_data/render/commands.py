"""`rebar render`: a few frames of a pipeline's scenes, to look at before building a dataset."""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

from rebar_data.arguments import bounded

COMMAND = "rebar render"
FRAMES = bounded(int, 1)
SEED = bounded(int, 0, 2**32 - 1)
_FRAME = re.compile(r"frame_\d{3,}_\w+\.png")


def is_render_folder(folder: Path) -> bool:
    """``folder`` has the layout of an earlier `rebar render` output: its contact sheet and frames only."""
    names = [p.name for p in folder.iterdir()]
    return "contact_sheet.png" in names and all(
        n == "contact_sheet.png" or _FRAME.fullmatch(n) for n in names
    )


def run_render(args: argparse.Namespace) -> None:
    import numpy as np

    from rebar_data.geometry.build import build_rebar_mesh
    from rebar_data.outputs import OutputLock, mark_output, output_folder, remove_stale, replace_folder
    from rebar_data.pipeline import load_pipeline
    from rebar_data.render.engines import check_engine
    from rebar_data.scene.cameras import intrinsics_from_config

    def check_out() -> Path:
        return output_folder(args.out, arg="--out", command=COMMAND, owned=is_render_folder, swapped=True)

    final = check_out()
    cfg = load_pipeline(args.config)
    check_engine(cfg.render)
    rm = build_rebar_mesh(cfg.mesh_config())
    k = intrinsics_from_config(cfg.camera)
    rng = np.random.default_rng(cfg.seed if args.seed is None else args.seed)
    with OutputLock(final, command=COMMAND):
        check_out()  # again under the lock: another writer may have finished there meanwhile
        remove_stale(final.parent, f".{final.name}.tmp-*")  # a killed run's (the lock proves it dead)
        # frames go to a folder beside --out, swapped in whole at the end
        with tempfile.TemporaryDirectory(dir=final.parent, prefix=f".{final.name}.tmp-") as tmp:
            out = Path(tmp) / "frames"
            out.mkdir()
            n = _render_frames(cfg, rm, k, rng, args.frames, out)
            mark_output(out, COMMAND)
            replace_folder(out, final)
    print(f"{n} frames, {k.width}x{k.height}, contact sheet contact_sheet.png", file=sys.stderr)
    print(final)


def _render_frames(cfg, rm, k, rng, frames: int, out: Path) -> int:
    """Render ``frames`` frames of new scenes and their contact sheet into ``out``; returns how many."""
    import cv2
    import numpy as np
    from tqdm import tqdm

    from rebar_data.render.engines import renderer_class
    from rebar_data.scene.cameras import trajectory_poses
    from rebar_data.scene.sample import sample_scene, sample_sensor

    thumbs = []
    with renderer_class(cfg.render)(k, cfg.render) as renderer:
        renderer.set_mesh(rm)
        for i in tqdm(range(frames), desc="render", unit="frame", file=sys.stderr):
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
    return len(thumbs)


def register(sub: argparse._SubParsersAction) -> None:
    r = sub.add_parser("render", help="render a few frames of a pipeline's scenes to PNG, to look at")
    r.add_argument("config", help="pipeline YAML, such as pipelines/paper-tunnel.yaml")
    r.add_argument(
        "--out",
        required=True,
        help="output folder: new, empty, or an earlier `rebar render` output, which is replaced whole",
    )
    r.add_argument("--frames", type=FRAMES, default=8, help=f"frames, each a new scene ({FRAMES}; default 8)")
    r.add_argument("--seed", type=SEED, help=f"seed ({SEED}; default: the pipeline's)")
    r.set_defaults(func=run_render)
