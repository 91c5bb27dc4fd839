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

import logging
import os
import socket
from collections.abc import Iterator
from pathlib import Path

from rebar_data.config import ConfigError
from rebar_data.dataset import layout
from rebar_data.dataset.build import Task, build_dataset, check_paths, check_workers, plural
from rebar_data.dataset.worker import FrameRecord, FrameWorker
from rebar_data.geometry.build import RebarMesh
from rebar_data.pipeline import PipelineConfig, load_pipeline

RAY_INSTALL_HINT = "pip install -e '.[ray]' (or pip install 'ray>=2.30,<3')"
SHARDS_IN_FLIGHT_PER_ACTOR = 2  # one running, one queued, so an actor never waits for the driver


class BackendError(RuntimeError):
    """A shard failed on the cluster after Ray's retries; finished shards are kept for ``--resume``."""


def import_ray():
    """Ray, or one clear ConfigError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ConfigError(
            f"--backend ray needs the ray package, which is not installed; accepted: {RAY_INSTALL_HINT}, "
            "or --backend local"
        ) from None
    return ray


class RenderActor:
    """One renderer per actor process; runs shards one after another (wrapped by ``ray.remote``)."""

    def __init__(self, cfg: PipelineConfig, staging: str, worker_cls: type[FrameWorker] = FrameWorker):
        os.environ.setdefault("EGL_PLATFORM", "surfaceless")
        os.environ.setdefault("LP_NUM_THREADS", "1")  # one rasteriser thread: an actor has one CPU
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
        address = self.address or os.environ.get("RAY_ADDRESS", "")
        if address and not _answers(address):
            raise ConfigError(
                f"--address {address}: no Ray cluster answers there; accepted: the HOST:PORT that "
                "`ray start --head` printed, or auto on a node of a running cluster"
            )

    def _connect(self, ray) -> bool:
        """Join or start a cluster; True when this call started it (and so must shut it down)."""
        if ray.is_initialized():
            return False
        kwargs: dict = {"log_to_driver": False, "logging_level": logging.ERROR}
        if self.address is None and not os.environ.get("RAY_ADDRESS"):
            kwargs.update(num_cpus=self.actors or os.cpu_count() or 1, include_dashboard=False)
        else:
            kwargs["address"] = self.address
            self.check_address()
        try:
            ray.init(**kwargs)
        except ConnectionError as e:
            raise ConfigError(
                f"--address {self.address or os.environ.get('RAY_ADDRESS')}: no Ray cluster answers there "
                f"({e}); accepted: the address `ray start --head` printed, or auto"
            ) from None
        return True

    def __call__(
        self, cfg: PipelineConfig, rm: RebarMesh, staging: Path, tasks: list[Task]
    ) -> Iterator[tuple[str, list[FrameRecord]]]:
        if not tasks:
            return
        ray = import_ray()
        started = self._connect(ray)
        pool = []
        try:
            n = self.actors or int(ray.cluster_resources().get("CPU", 1))
            n = max(1, min(n, len(tasks)))
            self.label = plural(n, "Ray actor")
            actor_cls = ray.remote(
                num_cpus=1, max_restarts=self.max_restarts, max_task_retries=self.max_task_retries
            )(RenderActor)
            pool = [actor_cls.remote(cfg, str(staging), self.worker_cls) for _ in range(n)]
            yield from _dispatch(ray, pool, tasks)
            _check_shared_filesystem(staging, tasks)
        finally:
            for actor in pool:
                ray.kill(actor)
            if started:
                ray.shutdown()


def _answers(address: str, timeout_s: float = 5.0) -> bool:
    """Whether a HOST:PORT address accepts a connection (Ray itself waits minutes for a missing head).
    Other forms (auto, ray://...) are left to Ray."""
    host, sep, port = address.rpartition(":")
    if not sep or "/" in address or not port.isdigit():
        return True
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s):
            return True
    except OSError:
        return False


def _dispatch(ray, pool: list, tasks: list[Task]) -> Iterator[tuple[str, list[FrameRecord]]]:
    """Hand shards to actors as they free up (a few queued per actor) and yield results as they finish."""
    pending = list(reversed(tasks))
    in_flight: dict = {}

    def submit(actor) -> None:
        task = pending.pop()
        in_flight[actor.run.remote(task)] = (actor, task[0])

    for _ in range(SHARDS_IN_FLIGHT_PER_ACTOR):
        for actor in pool:
            if pending:
                submit(actor)
    while in_flight:
        ready, _ = ray.wait(list(in_flight), num_returns=1)
        actor, trajectory_id = in_flight.pop(ready[0])
        try:
            result = ray.get(ready[0])
        except (ray.exceptions.RayActorError, ray.exceptions.RayTaskError) as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise BackendError(
                f"shard {trajectory_id} failed on the Ray cluster after its retries: {first}; the shards that "
                "finished are kept, run the same build again with --resume to continue"
            ) from e
        if pending:
            submit(actor)
        yield result


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
