"""``rebar dataset build``: plan, render and label in parallel, then write every format and finalise.

The build works in a staging folder beside the target (``<root>/<name>/.v<version>.partial``) and
renames it into place only when everything is written, so an interrupted build never leaves a folder
that looks finished. Finished trajectories are kept in the staging folder; ``--resume`` continues from
them and ends with the same dataset as an uninterrupted build.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import pickle
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

from tqdm import tqdm

import rebar_data
from rebar_data.config import ConfigError
from rebar_data.dataset import layout
from rebar_data.dataset.config import PipelineConfig, load_pipeline
from rebar_data.dataset.layout import DatasetInfo
from rebar_data.dataset.plan import Plan, Sample, make_plan
from rebar_data.dataset.worker import FrameRecord, FrameWorker, init_process, run_in_process
from rebar_data.dataset.writers.card import write_card
from rebar_data.dataset.writers.coco import write_coco
from rebar_data.dataset.writers.manifest import write_manifest
from rebar_data.dataset.writers.tables import keypoints_table, samples_table, write_tables
from rebar_data.dataset.writers.yolo import write_data_yaml, write_yolo
from rebar_data.geometry.build import RebarMesh, build_rebar_mesh
from rebar_data.render.engines import check_engine, engine_record
from rebar_data.scene.cameras import intrinsics_from_config
from rebar_data.scene.sample import SceneSample

PLAN_FILE = "plan.json"
RECORDS = "records"

Task = tuple[str, SceneSample, list[Sample]]
"""One shard of work: a trajectory id, its scene and its samples (the frames of the trajectory)."""


class TaskRunner(Protocol):
    """Runs shards and yields ``(trajectory_id, records)`` as each one finishes, in any order.

    A runner renders into ``staging`` (images, depth and instance maps, written via temporary names) and
    returns the labels; the build saves the records of each finished shard and finalises, so every
    backend that runs the same tasks ends with the same dataset.
    """

    label: str  # how the summary line names the workers, such as "2 workers"

    def __call__(
        self, cfg: PipelineConfig, rm: RebarMesh, staging: Path, tasks: list[Task]
    ) -> Iterator[tuple[str, list[FrameRecord]]]: ...


class LocalRunner:
    """The local backend: this process with one worker, a spawn process pool with more."""

    def __init__(self, workers: int):
        self.workers = workers
        self.label = f"{workers} workers"

    def __call__(
        self, cfg: PipelineConfig, rm: RebarMesh, staging: Path, tasks: list[Task]
    ) -> Iterator[tuple[str, list[FrameRecord]]]:
        return _run_tasks(cfg, rm, staging, tasks, self.workers)


def git_commit() -> str:
    """The commit of the package's checkout ("-dirty" when it has changes), or "unknown"."""
    here = Path(rebar_data.__file__).resolve().parent
    try:
        head = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + ("-dirty" if dirty else "")


def staging_dir(final: Path) -> Path:
    return final.parent / f".{final.name}.partial"


def prepare_staging(cfg: PipelineConfig, final: Path, *, force: bool, resume: bool) -> Path:
    """Check what is on disk against the flags; return the staging folder to work in."""
    staging = staging_dir(final)
    if final.exists() and not force:
        raise ConfigError(
            f"{final} already exists; accepted: --force to rebuild it, or a new version in the config"
        )
    if staging.exists():
        if resume:
            plan = json.loads((staging / PLAN_FILE).read_text()) if (staging / PLAN_FILE).exists() else {}
            if plan.get("config_hash") != cfg.config_hash():
                raise ConfigError(
                    f"{staging} was started from a different config; accepted: the same config with "
                    "--resume, or --force to start over"
                )
        elif force:
            shutil.rmtree(staging)
        else:
            raise ConfigError(
                f"an interrupted build is at {staging}; accepted: --resume to continue it or --force to start over"
            )
    (staging / RECORDS).mkdir(parents=True, exist_ok=True)
    (staging / PLAN_FILE).write_text(json.dumps({"config_hash": cfg.config_hash()}, sort_keys=True))
    return staging


def _load_done(staging: Path) -> dict[str, list[FrameRecord]]:
    done = {}
    for p in sorted((staging / RECORDS).glob("*.pkl")):
        with open(p, "rb") as f:
            done[p.stem] = pickle.load(f)
    return done


def _save_records(staging: Path, trajectory_id: str, records: list[FrameRecord]) -> None:
    path = staging / RECORDS / f"{trajectory_id}.pkl"
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        pickle.dump(records, f, protocol=pickle.HIGHEST_PROTOCOL)
    tmp.replace(path)


def _run_tasks(
    cfg: PipelineConfig, rm: RebarMesh, staging: Path, tasks: list, workers: int
) -> Iterator[tuple[str, list[FrameRecord]]]:
    if workers <= 1 or len(tasks) <= 1:
        worker = FrameWorker(cfg, staging, rm)
        try:
            for tid, scene, samples in tasks:
                yield tid, worker.run(scene, samples)
        finally:
            worker.close()
        return
    # spawn, not fork: a process forked after EGL and Filament were initialised in the parent can hang.
    # Each worker rebuilds the mesh from the config (deterministic, under a second).
    ctx = mp.get_context("spawn")
    with ctx.Pool(min(workers, len(tasks)), initializer=init_process, initargs=(cfg, staging, None)) as pool:
        yield from pool.imap_unordered(run_in_process, tasks)


def build_dataset(
    config: str | Path,
    out_root: str | Path,
    *,
    workers: int | None = None,
    force: bool = False,
    resume: bool = False,
    runner: TaskRunner | None = None,
) -> Path:
    """Build the dataset described by ``config`` under ``out_root`` and return its folder.

    ``runner`` runs the shards (default: the local backend with ``workers`` processes); the plan, the
    staging folder, resume and finalize are the same whatever runs them.
    """
    cfg = load_pipeline(config)
    check_engine(cfg.render)
    final = layout.dataset_dir(Path(out_root), cfg.name, cfg.version).resolve()
    workers = workers or os.cpu_count() or 1
    runner = runner or LocalRunner(workers)
    staging = prepare_staging(cfg, final, force=force, resume=resume)
    t0 = time.perf_counter()
    rm = build_rebar_mesh(cfg.mesh_config())
    plan = make_plan(cfg, rm)
    done = _load_done(staging)
    tasks = [
        (t.trajectory_id, plan.scenes[t.scene_index], plan.samples_of(t.trajectory_id))
        for t in plan.trajectories
        if t.trajectory_id not in done
    ]
    n_done = sum(len(v) for v in done.values())
    bar = tqdm(
        total=len(plan.samples),
        initial=n_done,
        desc=f"{cfg.name} v{cfg.version}",
        unit="img",
        file=sys.stderr,
    )
    for tid, records in runner(cfg, rm, staging, tasks):
        _save_records(staging, tid, records)
        done[tid] = records
        bar.update(len(records))
    bar.close()
    _remove_stray_temp_files(staging)
    records = {r.image_id: r for recs in done.values() for r in recs}
    info = finalize(cfg, rm, plan, records, staging, final)
    dt = time.perf_counter() - t0
    c = info.counts
    print(
        f"{len(records)} images (train {c['train']['images']}, val {c['val']['images']}, test {c['test']['images']}), "
        f"{sum(c[s]['visible'] for s in layout.SPLITS)} visible keypoints, {dt:.1f} s "
        f"({(len(records) - n_done) / max(dt, 1e-9):.2f} img/s with {runner.label})",
        file=sys.stderr,
    )
    return final


def _remove_stray_temp_files(staging: Path) -> None:
    """Remove half-written files of workers that were killed mid-write (a retried shard rewrites them)."""
    for p in staging.rglob(".*.tmp"):
        p.unlink(missing_ok=True)


def _counts(plan: Plan, records: dict[str, FrameRecord]) -> dict:
    counts = {
        s: {"images": 0, "keypoints": 0, "visible": 0, "occluded": 0, "outside": 0} for s in layout.SPLITS
    }
    for s in plan.samples:
        vis = records[s.image_id].labels.visibility
        c = counts[s.split]
        c["images"] += 1
        c["keypoints"] += len(vis)
        c["visible"] += int((vis == 2).sum())
        c["occluded"] += int((vis == 1).sum())
        c["outside"] += int((vis == 0).sum())
    return counts


def make_info(cfg: PipelineConfig, plan: Plan, records: dict[str, FrameRecord]) -> DatasetInfo:
    k = intrinsics_from_config(cfg.camera)
    split = cfg.dataset.split
    return DatasetInfo(
        name=cfg.name,
        version=cfg.version,
        schema_version=layout.SCHEMA_VERSION,
        generator={"name": "rebar-data", "version": rebar_data.__version__, "git_commit": git_commit()},
        config=cfg.resolved(),
        config_hash=cfg.config_hash(),
        seed=cfg.seed,
        counts=_counts(plan, records),
        split={
            "rule": split.rule,
            "fractions": {"train": split.train, "val": split.val, "test": split.test},
            "groups": plan.groups,
        },
        image_size={"width": k.width, "height": k.height},
        intrinsics={
            "fx": k.fx,
            "fy": k.fy,
            "cx": k.cx,
            "cy": k.cy,
            "convention": "u = fx * x / z + cx, COCO corner origin",
        },
        keypoint_names=list(layout.KEYPOINT_NAMES),
        oks_sigma=cfg.dataset.oks_sigma,
        oks_area="box_size_px ** 2 (the unclipped square box of the keypoint)",
        conventions={
            "units": "SI (metres, radians); pixels for u, v and box_size_px",
            "camera": "OpenCV: x right, y down, z forward",
            "transforms": "a_from_b; world_from_camera maps camera points into the world (row-major 4x4)",
            "visibility": "0 outside the image, 1 inside but occluded, 2 visible",
            "yolo_coco_objects": "visible keypoints (visibility 2) only",
            "depth_png": "uint16 millimetres of camera-frame z, 0 = no hit",
            "instance_png": "uint16 instance id + 3: 0 distractor, 1 ground/background, 2 nothing, 3+ rebar part id + 3",
        },
        description=cfg.description,
        renderer=engine_record(cfg.render),
    )


def finalize(
    cfg: PipelineConfig,
    rm: RebarMesh,
    plan: Plan,
    records: dict[str, FrameRecord],
    staging: Path,
    final: Path,
) -> DatasetInfo:
    """Write tables, YOLO, COCO, info and manifest into ``staging``, then rename it to ``final``."""
    k = intrinsics_from_config(cfg.camera)
    ds = cfg.dataset
    samples = samples_table(plan, records, k, depth=ds.store_depth, instances=ds.store_instances)
    keypoints = keypoints_table(plan, records, rm)
    write_tables(staging, samples, keypoints)
    write_yolo(staging, samples, keypoints)
    write_data_yaml(staging, final, oks_sigma=ds.oks_sigma)
    info = make_info(cfg, plan, records)
    coco_info = {"description": f"{cfg.name} v{cfg.version}", "version": cfg.version}
    write_coco(staging, samples, keypoints, coco_info)
    info.write(staging / layout.INFO)
    write_card(staging, info)
    shutil.rmtree(staging / RECORDS)
    (staging / PLAN_FILE).unlink()
    write_manifest(staging)
    if final.exists():
        shutil.rmtree(final)
    staging.rename(final)
    return info
