"""Frames do not depend on what a process rendered before: two processes, two orders, the same bytes."""

from __future__ import annotations

import json
import os
import subprocess
import sys

SCRIPT = r"""
import hashlib, json, sys
import numpy as np
from rebar_data.geometry.config import MeshConfig
from rebar_data.geometry.build import build_rebar_mesh
from rebar_data.render.renderer import Renderer
from rebar_data.camera import Intrinsics
from rebar_data.scene.cameras import trajectory_poses
from rebar_data.scene.config import CameraConfig, RenderConfig, SceneConfig
from rebar_data.scene.sample import sample_scene, sample_sensor
from tests.scene.conftest import TUNNEL

rm = build_rebar_mesh(MeshConfig.model_validate(TUNNEL))
r = Renderer(Intrinsics(160, 120, 150.0, 150.0, 80.0, 60.0), RenderConfig(texture_size_px=256, cache_dir=sys.argv[2]))
r.set_mesh(rm)
cam = CameraConfig()
out = {}
for seed in json.loads(sys.argv[1]):
    rng = np.random.default_rng(seed)
    scene = sample_scene(SceneConfig(), rng)
    r.set_scene(scene)
    pose = trajectory_poses(cam.trajectories[seed % 3], rm, rng)[3]
    f = r.render(pose, sample_sensor(SceneConfig(), rng), rng)
    out[seed] = [hashlib.sha256(a.tobytes()).hexdigest() for a in (f.rgb, f.depth_m, f.instance)]
print(json.dumps(out))
"""


def _run(order, root, cache):
    env = {**os.environ, "EGL_PLATFORM": "surfaceless", "PYTHONPATH": str(root)}
    p = subprocess.run(
        [sys.executable, "-c", SCRIPT, json.dumps(order), str(cache)],
        capture_output=True,
        text=True,
        env=env,
        cwd=root,
        timeout=300,
    )
    assert p.returncode == 0, p.stderr[-2000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


def test_same_frames_whatever_the_order_and_process(root, tmp_path):
    # seeds chosen so the scenes differ in shadows, lamps and ground; the first frame of each process
    # is a different scene
    a = _run([1, 2, 3], root, tmp_path)
    b = _run([3, 1, 2], root, tmp_path)
    assert a == b
    assert len({v[0] for v in a.values()}) == 3
