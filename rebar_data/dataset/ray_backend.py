"""The Ray backend of ``rebar dataset build``: the local build's plan and finalize, its shards on a Ray cluster.

The driver plans every sample exactly as the local backend does (``plan.py``), then hands shards (one
camera trajectory each: its scene and frames) to long-lived actors. Each actor owns one ``FrameWorker``,
so Open3D's renderer, which is expensive to create, is built once per actor and reused for every shard.
Actors write images into the build's staging folder, which must be on a filesystem every node shares,
and return the labels; the driver saves each finished shard's records and finalises exactly as the local
build does, so labels, tables and the manifest are byte-identical to the local backend's.

A worker that dies mid-shard is restarted by Ray and the shard is run again from its start: image files
are written via temporary names and renamed, and records are saved per finished shard, so a retried
shard neither duplicates nor loses samples.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from rebar_data.dataset import layout
from rebar_data.dataset.build import Task, build_dataset, check_paths, plural
from rebar_data.dataset.worker import FrameRecord, FrameWorker
from rebar_data.geometry.build import RebarMesh
from rebar_data.pipeline import PipelineConfig, load_pipeline
from rebar_data.ray_cluster import (
    BackendError,
    check_address,
    import_ray,
    on_actors,
)
from rebar_data.workers import check_workers, renderer_process


class RenderActor:
    """One renderer per actor process; runs shards one after another (wrapped by ``ray.remote``)."""

    def __init__(self, cfg: PipelineConfig, staging: str, worker_cls: type[FrameWorker] = FrameWorker):
        renderer_process(answers_ctrl_c=True)
        self.worker = worker_cls(cfg, Path(staging))

    def run(self, task: Task) -> tuple[str, list[FrameRecord]]:
        trajectory_id, scene, samples = task
        return trajectory_id, self.worker.run(scene, samples)


class RayRunner:
    """Runs build shards on Ray actors (see the module docstring).

    Args:
        address: the cluster to join (``ray start --head`` prints it; ``auto`` finds one on this machine).
            None joins ``RAY_ADDRESS`` when set, else starts a private local cluster for this build.
        actors: actors (renderers) to start; default one per CPU of the cluster.
        max_restarts: times Ray restarts an actor whose process died.
        max_task_retries: times Ray runs a shard again after its actor died.
        worker_cls: the per-actor worker; a ``FrameWorker`` unless a test injects faults.
    """

    def __init__(
        self,
        *,
        address: str | None = None,
        actors: int | None = None,
        max_restarts: int = 3,
        max_task_retries: int = 3,
        worker_cls: type[FrameWorker] = FrameWorker,
    ):
        self.address = address
        self.actors = actors
        self.max_restarts = max_restarts
        self.max_task_retries = max_task_retries
        self.worker_cls = worker_cls
        self.label = "Ray actors"

    def check_address(self) -> None:
        """One clear ConfigError when the cluster to join does not answer (checked before any work)."""
        check_address(self.address)

    def __call__(
        self, cfg: PipelineConfig, rm: RebarMesh, staging: Path, tasks: list[Task]
    ) -> Iterator[tuple[str, list[FrameRecord]]]:
        yield from on_actors(
            RenderActor,
            (cfg, str(staging), self.worker_cls),
            tasks,
            address=self.address,
            actors=self.actors,
            name=lambda t: f"shard {t[0]}",
            again="the shards that finished are kept, run the same build again with --resume to continue",
            max_restarts=self.max_restarts,
            max_task_retries=self.max_task_retries,
            sized=lambda n: setattr(self, "label", plural(n, "Ray actor")),
        )
        _check_shared_filesystem(staging, tasks)


def _check_shared_filesystem(staging: Path, tasks: list[Task]) -> None:
    """Every image an actor wrote must be visible here; otherwise the nodes do not share ``--out``."""
    for _, _, samples in tasks:
        for s in samples:
            p = staging / layout.image_path(s.split, s.image_id)
            if not p.exists():
                raise BackendError(
                    f"{p} was rendered on the cluster but is not in the output folder here: --out must be a "
                    "folder on a filesystem that every Ray node mounts at the same path"
                )


def build_dataset_ray(
    config: str | Path,
    out_root: str | Path,
    *,
    address: str | None = None,
    actors: int | None = None,
    force: bool = False,
    resume: bool = False,
) -> Path:
    """``build_dataset`` with its shards run on a Ray cluster; the same dataset, byte for byte, in its labels.

    The driver (this process) holds the dataset's lock, as a local build does.
    """
    check_paths(config, out_root)
    check_workers(actors, backend="ray")
    cfg = load_pipeline(config)  # a broken pipeline is the first thing reported, before Ray or the cluster
    import_ray()
    runner = RayRunner(address=address, actors=actors)
    runner.check_address()
    return build_dataset(
        config, out_root, workers=actors, force=force, resume=resume, runner=runner, pipeline=cfg
    )
