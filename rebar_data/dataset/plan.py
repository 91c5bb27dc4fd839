"""The per-sample plan of a dataset build: scenes, trajectories, frames, seeds and splits.

Everything random is drawn here from the config's seed through ``SeedSequence`` children with fixed
spawn keys, before any work is handed out, so the plan (and therefore every label and table) is the
same whatever the number of workers or backend.

A *scene* is one draw of lights, rebar material and surroundings. Scene ``k`` is filmed by instance
``k`` of every trajectory kind in ``camera.trajectories`` (the paper: one mesh, three lights, three
camera trajectories), so each scene holds one trajectory of each kind.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rebar_data.dataset.layout import SPLITS
from rebar_data.geometry.build import RebarMesh
from rebar_data.pipeline import PipelineConfig, SplitConfig
from rebar_data.scene.cameras import trajectory_poses
from rebar_data.scene.sample import SceneSample, sample_scene

# spawn keys of the independent seed streams (the mesh uses SeedSequence(seed).spawn directly)
_SCENES, _TRAJECTORIES, _FRAMES, _SPLITS = 101, 102, 103, 104
_DEPTH_SENSOR = 105  # below a sample's own stream


def depth_sensor_seed(sample_seed: np.random.SeedSequence) -> np.random.SeedSequence:
    """The stream of a sample's depth sensor draws: a child of the sample's stream that nothing else uses,
    so the depth sensor leaves the sample's other draws (its sensor effects, the render noise) untouched."""
    return np.random.SeedSequence(sample_seed.entropy, spawn_key=(*sample_seed.spawn_key, _DEPTH_SENSOR))


@dataclass(frozen=True)
class Trajectory:
    trajectory_id: str
    scene_id: str
    scene_index: int
    kind: str
    world_from_camera: np.ndarray  # (frames, 4, 4)


@dataclass(frozen=True)
class PlannedImage:
    index: int
    image_id: str
    split: str
    trajectory_id: str
    scene_id: str
    frame: int
    world_from_camera: np.ndarray  # (4, 4)
    seed: np.random.SeedSequence  # per-sample stream: sensor effects and render noise


@dataclass(frozen=True)
class Plan:
    scenes: list[SceneSample]
    trajectories: list[Trajectory]
    samples: list[PlannedImage]
    groups: dict[str, list[str]]  # split -> scene/trajectory ids (empty for the random rule)

    def samples_of(self, trajectory_id: str) -> list[PlannedImage]:
        return [s for s in self.samples if s.trajectory_id == trajectory_id]


def _stream(seed: int, key: int, n: int) -> list[np.random.SeedSequence]:
    return np.random.SeedSequence(seed, spawn_key=(key,)).spawn(n)


def allocate(n: int, cfg: SplitConfig) -> list[int]:
    """Items per split (train, val, test) by largest remainder; every split with a positive fraction
    gets at least one item when there are enough items for that."""
    fractions = np.array([cfg.train, cfg.val, cfg.test])
    counts = np.floor(fractions * n).astype(int)
    for i in np.argsort(-(fractions * n - counts), kind="stable")[: n - counts.sum()]:
        counts[i] += 1
    wanted = fractions > 0
    if n >= wanted.sum():
        for i in np.nonzero(wanted & (counts == 0))[0]:
            donor = int(np.argmax(counts))
            counts[donor] -= 1
            counts[i] += 1
    return [int(c) for c in counts]


def assign_splits(ids: list[str], cfg: SplitConfig, seed: int) -> dict[str, str]:
    """Shuffle ``ids`` with the split stream and cut them into train/val/test."""
    rng = np.random.default_rng(_stream(seed, _SPLITS, 1)[0])
    order = [ids[i] for i in rng.permutation(len(ids))]
    out, start = {}, 0
    for split, n in zip(SPLITS, allocate(len(ids), cfg), strict=True):
        for item in order[start : start + n]:
            out[item] = split
        start += n
    return out


def make_plan(cfg: PipelineConfig, rm: RebarMesh) -> Plan:
    trajs_cfg = cfg.camera.trajectories
    n_scenes = max(t.count for t in trajs_cfg)
    scene_seeds = _stream(cfg.seed, _SCENES, n_scenes)
    scenes = [sample_scene(cfg.scene, np.random.default_rng(s)) for s in scene_seeds]
    n_traj = sum(t.count for t in trajs_cfg)
    traj_seeds = iter(_stream(cfg.seed, _TRAJECTORIES, n_traj))
    trajectories = []
    for ti, tcfg in enumerate(trajs_cfg):
        for k in range(tcfg.count):
            poses = trajectory_poses(tcfg, rm, np.random.default_rng(next(traj_seeds)))
            tid = f"s{k:03d}-t{ti}-{tcfg.kind}"
            trajectories.append(Trajectory(tid, f"s{k:03d}", k, tcfg.kind, poses))
    trajectories.sort(key=lambda t: t.trajectory_id)
    frames = [(t, f) for t in trajectories for f in range(len(t.world_from_camera))]
    frame_seeds = _stream(cfg.seed, _FRAMES, len(frames))
    image_ids = [f"{t.trajectory_id}-f{f:03d}" for t, f in frames]
    rule = cfg.dataset.split.rule
    if rule == "random":
        split_of = assign_splits(image_ids, cfg.dataset.split, cfg.seed)
        groups: dict[str, list[str]] = {s: [] for s in SPLITS}
    else:
        group_ids = sorted({(t.scene_id if rule == "scene" else t.trajectory_id) for t in trajectories})
        group_split = assign_splits(group_ids, cfg.dataset.split, cfg.seed)
        groups = {s: sorted(g for g, gs in group_split.items() if gs == s) for s in SPLITS}
        split_of = {
            iid: group_split[t.scene_id if rule == "scene" else t.trajectory_id]
            for iid, (t, _) in zip(image_ids, frames, strict=True)
        }
    samples = [
        PlannedImage(
            i, iid, split_of[iid], t.trajectory_id, t.scene_id, f, t.world_from_camera[f], frame_seeds[i]
        )
        for i, (iid, (t, f)) in enumerate(zip(image_ids, frames, strict=True))
    ]
    return Plan(scenes, trajectories, samples, groups)
