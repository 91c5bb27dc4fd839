"""``rebar dataset build``: plan, render and label in parallel, then write every format and finalise.

The build works in a staging folder beside the target (``<root>/<name>/.v<version>.partial``) and
swaps it into place only when everything is written (``outputs.replace_folder``), so an interrupted build
never leaves a folder that looks finished and ``--force`` never leaves the path without a dataset.
Finished trajectories are kept in the staging folder; ``--resume`` continues from them and ends with the
same dataset as an uninterrupted build. One build at a time writes a dataset: the build holds an
``OutputLock`` on the dataset's folder from before it looks at the staging folder until it ends, so a
second build is told which live process writes there, and a staging folder with no live holder is an
interrupted build. Ctrl-C ends the workers quietly and leaves a staging folder that ``--resume`` continues.
"""

from __future__ import annotations

import json
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
from rebar_data.dataset.layout import DatasetInfo
from rebar_data.dataset.plan import Plan, PlannedImage, make_plan
from rebar_data.dataset.worker import FrameRecord, FrameWorker, init_process, run_in_process
from rebar_data.dataset.writers.card import write_card
from rebar_data.dataset.writers.coco import write_coco
from rebar_data.dataset.writers.manifest import write_manifest
from rebar_data.dataset.writers.tables import keypoints_table, samples_table, write_tables
from rebar_data.dataset.writers.yolo import write_data_yaml, write_yolo
from rebar_data.geometry.build import RebarMesh, build_rebar_mesh
from rebar_data.outputs import (
    OutputLock,
    input_file,
    output_folder,
    replace_folder,
    restore_interrupted_swap,
    space_for,
)
from rebar_data.pipeline import PipelineConfig, load_pipeline
from rebar_data.render.engines import check_engine, engine_record
from rebar_data.scene.cameras import intrinsics_from_config
from rebar_data.scene.sample import SceneSample
from rebar_data.workers import check_workers, spawned_pool_map

COMMAND = "rebar dataset build"
PLAN_FILE = "plan.json"
RECORDS = "records"

Task = tuple[str, SceneSample, list[PlannedImage]]
"""One shard of work: a trajectory id, its scene and its samples (the frames of the trajectory)."""


class TaskRunner(Protocol):
    """Runs shards and yields ``(trajectory_id, records)`` as each one finishes, in any order.

    A runner renders into ``staging`` (images, depth and instance maps, written via temporary names) and
    returns the labels; the build saves the records of each finished shard and finalises, so every
    backend that runs the same tasks ends with the same dataset.
    """

    label: str  # how the summary line names the workers, such as "2 workers" (set once it knows)

    def __call__(
        self, cfg: PipelineConfig, rm: RebarMesh, staging: Path, tasks: list[Task]
    ) -> Iterator[tuple[str, list[FrameRecord]]]: ...


class LocalRunner:
    """The local backend: this process with one worker, a spawn process pool with more."""

    def __init__(self, workers: int):
        self.workers = workers
        self.label = plural(workers, "worker")

    def __call__(
        self, cfg: PipelineConfig, rm: RebarMesh, staging: Path, tasks: list[Task]
    ) -> Iterator[tuple[str, list[FrameRecord]]]:
        self.label = plural(_processes(self.workers, tasks), "worker")
        return _run_tasks(cfg, rm, staging, tasks, self.workers)


class BuildInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped a build; the message is the one-line summary (what was done, how to go on)."""


def plural(n: int, noun: str) -> str:
    """``1 worker``, ``2 workers``."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


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


def finishing_dir(final: Path) -> Path:
    """Where ``finalize`` keeps the records and plan out of the dataset's files until the swap is done."""
    return final.parent / f".{final.name}.finishing"


def check_paths(config: str | Path, out_root: str | Path) -> Path:
    """The pipeline is a readable file and ``--out`` a folder (new or not) there is a place to write; one
    ConfigError line otherwise, before any work. Returns the pipeline's path (read once, by
    ``load_pipeline``, which also refuses a file that is not text)."""
    path = input_file(config, arg="pipeline", what="a pipeline YAML file such as pipelines/smoke.yaml")
    out = Path(out_root)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: is a file; accepted: a folder to hold datasets, new or existing")
    return path


def is_dataset_of(folder: Path, cfg: PipelineConfig) -> bool:
    """``folder`` is a dataset this command wrote for ``cfg``: its meta/info.json names the same name and
    version (the only folders ``--force`` may replace)."""
    try:
        info = json.loads((Path(folder) / layout.INFO).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(info, dict) and (info.get("name"), info.get("version")) == (cfg.name, cfg.version)


def check_final(cfg: PipelineConfig, final: Path, *, force: bool) -> None:
    """The dataset's folder may be written: new, or with ``force`` this build's own earlier dataset, and
    the folder it lies in is writable (the build works beside it and swaps it in)."""
    output_folder(final, arg="--out", command=COMMAND, owned=lambda p: is_dataset_of(p, cfg))
    if final.exists() and not os.access(final.parent, os.W_OK | os.X_OK):
        raise ConfigError(f"--out {final.parent}: not writable; accepted: a folder you may write to")
    if final.exists() and not force:
        staging = staging_dir(final)
        flags = f"--force --resume to finish the rebuild at {staging}, " if staging.exists() else ""
        raise ConfigError(
            f"{final} already exists; accepted: {flags}--force to rebuild it, or a new version in the config"
        )


def _is_staging(staging: Path) -> bool:
    """A staging folder this command made (it writes the plan first), or an empty one."""
    if not staging.is_dir():
        return False
    return (staging / PLAN_FILE).exists() or (staging / RECORDS).is_dir() or not any(staging.iterdir())


def _recover_finishing(final: Path) -> None:
    """Put back what an interrupted ``finalize`` had moved aside: the records and plan into the staging
    folder when the swap had not happened, nothing (they are dropped) when it had."""
    aside, staging = finishing_dir(final), staging_dir(final)
    if not aside.exists():
        return
    if staging.exists():
        for name in (RECORDS, PLAN_FILE):
            if (aside / name).exists() and not (staging / name).exists():
                (aside / name).rename(staging / name)
    shutil.rmtree(aside)


def prepare_staging(cfg: PipelineConfig, final: Path, *, force: bool, resume: bool) -> Path:
    """Check what is on disk against the flags; return the staging folder to work in.

    Call it holding the dataset's ``OutputLock``: a staging folder then is an interrupted build's.
    """
    restore_interrupted_swap(final)
    _recover_finishing(final)
    check_final(cfg, final, force=force)
    staging = staging_dir(final)
    if staging.exists():
        if not _is_staging(staging):
            raise ConfigError(
                f"{staging} holds files that `{COMMAND}` did not write; accepted: move that folder away"
            )
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
    staging.mkdir(parents=True, exist_ok=True)
    plan_tmp = staging / f".{PLAN_FILE}.tmp"
    plan_tmp.write_text(json.dumps({"config_hash": cfg.config_hash()}, sort_keys=True))
    plan_tmp.replace(staging / PLAN_FILE)
    (staging / RECORDS).mkdir(exist_ok=True)
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
    try:
        with open(tmp, "wb") as f:
            pickle.dump(records, f, protocol=pickle.HIGHEST_PROTOCOL)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def _processes(workers: int, tasks: list) -> int:
    """How many renderers ``_run_tasks`` starts: one in this process, or a pool of up to ``workers``."""
    return 1 if workers <= 1 or len(tasks) <= 1 else min(workers, len(tasks))


def _run_tasks(
    cfg: PipelineConfig, rm: RebarMesh, staging: Path, tasks: list, workers: int
) -> Iterator[tuple[str, list[FrameRecord]]]:
    if _processes(workers, tasks) == 1:
        worker = FrameWorker(cfg, staging, rm)
        try:
            for tid, scene, samples in tasks:
                yield tid, worker.run(scene, samples)
        finally:
            worker.close()
        return
    # Spawned workers (rebar_data.workers), each rebuilding the mesh from the config (deterministic, under a
    # second); this process ends them when it stops the build.
    yield from spawned_pool_map(
        _processes(workers, tasks), init_process, (cfg, staging, None), run_in_process, tasks
    )


def build_dataset(
    config: str | Path,
    out_root: str | Path,
    *,
    workers: int | None = None,
    force: bool = False,
    resume: bool = False,
    runner: TaskRunner | None = None,
    pipeline: PipelineConfig | None = None,
) -> Path:
    """Build the dataset described by ``config`` under ``out_root`` and return its folder.

    ``runner`` runs the shards (default: the local backend with ``workers`` processes, 1 to the machine's
    cores); the checks, the lock, the plan, the staging folder, resume and finalize are the same whatever
    runs them. ``pipeline`` is ``config`` as a caller already read it (a pipe can be read only once).
    Ctrl-C raises ``BuildInterrupted`` (a ``KeyboardInterrupt``) with a one-line summary.
    """
    config = check_paths(config, out_root)
    if runner is None:
        check_workers(workers)
    cfg = pipeline if pipeline is not None else load_pipeline(config)
    check_engine(cfg.render)
    final = layout.dataset_dir(Path(out_root), cfg.name, cfg.version).resolve()
    check_final(cfg, final, force=force)  # before the lock, which makes the dataset's parent folder
    runner = runner or LocalRunner(workers or os.cpu_count() or 1)
    flags = "--force --resume" if force else "--resume"
    with OutputLock(final, command=COMMAND):
        staging = prepare_staging(cfg, final, force=force, resume=resume)
        then = f"; then `{flags}` continues the build from {staging}"
        try:
            with space_for(final.parent, lambda: build_bytes(cfg, staging), then=then):
                return _build(cfg, runner, staging, final, resume_flags=flags)
        except ConfigError:
            _remove_stray_temp_files(staging)  # what was half-written; the finished shards' records stay
            raise


def build_bytes(cfg: PipelineConfig, staging: Path) -> int:
    """About how much more the build needs: the images still to write, at what those written so far take
    with their maps (before there are any, their uncompressed size: RGB, and 16-bit exact and sensor depth
    and instance maps where stored), and a tenth more for the tables and views made from them."""
    plan_images = sum(t.count * t.frames for t in cfg.camera.trajectories)
    images = staging / "images"
    written = len(list(images.rglob("*.png"))) if images.is_dir() else 0
    staged = sum(p.stat().st_size for p in staging.rglob("*") if p.is_file())
    if written:
        per_image = staged / written
    else:
        k = intrinsics_from_config(cfg.camera)
        maps = 2 * cfg.dataset.store_depth + cfg.dataset.store_instances
        per_image = k.width * k.height * (3 + 2 * maps)
    return int(1.1 * per_image * max(plan_images - written, 0))


def _build(cfg: PipelineConfig, runner: TaskRunner, staging: Path, final: Path, *, resume_flags: str) -> Path:
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
    results = runner(cfg, rm, staging, tasks)
    try:
        for tid, records in results:
            _save_records(staging, tid, records)
            done[tid] = records
            bar.update(len(records))
    except KeyboardInterrupt:
        bar.close()
        saved = sum(len(v) for v in done.values())
        raise BuildInterrupted(
            f"interrupted after {saved} of {len(plan.samples)} images; `{resume_flags}` continues it"
        ) from None
    except BaseException:
        bar.close()  # the bar's line ends before the error's
        raise
    finally:
        close = getattr(results, "close", None)  # ends the workers however the loop ended
        if close is not None:
            close()
    bar.close()
    _remove_stray_temp_files(staging)
    records = {r.image_id: r for recs in done.values() for r in recs}
    try:
        info = finalize(cfg, rm, plan, records, staging, final)
    except KeyboardInterrupt:
        raise BuildInterrupted(
            f"interrupted while writing the dataset's files; `{resume_flags}` finishes it"
        ) from None
    dt = time.perf_counter() - t0
    c = info.counts
    visible = sum(c[s]["visible"] for s in layout.SPLITS)
    print(
        f"{plural(len(records), 'image')} (train {c['train']['images']}, val {c['val']['images']}, "
        f"test {c['test']['images']}), {plural(visible, 'visible keypoint')}, {dt:.1f} s "
        f"({(len(records) - n_done) / max(dt, 1e-9):.2f} img/s with {runner.label})",
        file=sys.stderr,
    )
    return final


def _remove_stray_temp_files(staging: Path) -> None:
    """Remove half-written files of workers that were killed mid-write (a retried shard rewrites them)."""
    for p in [*staging.rglob(".*.tmp"), *(staging / RECORDS).glob("*.tmp")]:
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
            "sensor_depth_png": "uint16 millimetres of z as the frame's depth sensor reports it, 0 = no measurement",
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
    """Write tables, YOLO, COCO, info, the IFC model a mesh was read from, and the manifest into
    ``staging``, then swap it in at ``final``.

    The records and plan are moved out of the staging folder (not deleted) before the manifest is taken
    and dropped after the swap, so a build stopped here is still resumable (``prepare_staging``).
    """
    k = intrinsics_from_config(cfg.camera)
    ds = cfg.dataset
    samples = samples_table(plan, records, k, depth=ds.store_depth, instances=ds.store_instances)
    keypoints = keypoints_table(plan, records, rm)
    write_tables(staging, samples, keypoints)
    write_yolo(staging, samples, keypoints)
    write_data_yaml(staging, oks_sigma=ds.oks_sigma)
    info = make_info(cfg, plan, records)
    coco_info = {"description": f"{cfg.name} v{cfg.version}", "version": cfg.version}
    write_coco(staging, samples, keypoints, coco_info)
    info.write(staging / layout.INFO)
    write_card(staging, info)
    aside = finishing_dir(final)
    aside.mkdir(exist_ok=True)
    for name in (RECORDS, PLAN_FILE):
        (staging / name).rename(aside / name)
    if cfg.mesh.kind == "ifc":
        shutil.copyfile(cfg.mesh.ifc_path, staging / layout.MESH_IFC)
    write_manifest(staging)
    replace_folder(staging, final)
    shutil.rmtree(aside)
    return info
