"""Joining a Ray cluster and handing work to its actors: what every command with ``--backend ray`` shares
(``rebar dataset build``, ``rebar servo map``).

A command names the cluster with ``--address`` (or ``RAY_ADDRESS``); without either it starts a private local
cluster of its own and shuts it down when done. An address where nothing answers is one clear ConfigError
before any work (Ray itself waits minutes for a missing head). :func:`on_actors` runs tasks on actors, a few queued on
each so that an actor never waits for the driver, and yields results as they finish; a task that fails after
Ray's retries is a :class:`BackendError`.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Callable, Iterator
from typing import Any

from rebar_data.config import ConfigError

RAY_INSTALL_HINT = "pip install -e '.[ray]' (or pip install 'ray>=2.30,<3')"
TASKS_IN_FLIGHT_PER_ACTOR = 2  # one running, one queued


class BackendError(RuntimeError):
    """A task failed on the cluster after Ray's retries; the command's finished work is kept for a rerun."""


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


def answers(address: str, timeout_s: float = 5.0) -> bool:
    """Whether a HOST:PORT address accepts a connection. Other forms (auto, ray://...) are left to Ray."""
    host, sep, port = address.rpartition(":")
    if not sep or "/" in address or not port.isdigit():
        return True
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s):
            return True
    except OSError:
        return False


def check_backend(backend: str, address: str | None) -> None:
    """``--address`` only with ``--backend ray``: one clear ConfigError otherwise."""
    if address and backend != "ray":
        raise ConfigError(f"--address {address} is for the Ray backend; accepted: --backend ray")


def check_address(address: str | None) -> None:
    """One clear ConfigError when the cluster to join (``address``, else ``RAY_ADDRESS``) does not answer."""
    address = address or os.environ.get("RAY_ADDRESS", "")
    if address and not answers(address):
        raise ConfigError(
            f"--address {address}: no Ray cluster answers there; accepted: the HOST:PORT that "
            "`ray start --head` printed, or auto on a node of a running cluster"
        )


def connect(ray, address: str | None, cpus: int | None) -> bool:
    """Join the cluster at ``address`` (or ``RAY_ADDRESS``), or start a private one of ``cpus`` CPUs (default:
    this machine's); True when this call started it (and so must shut it down)."""
    if ray.is_initialized():
        return False
    kwargs: dict = {"log_to_driver": False, "logging_level": logging.ERROR}
    if address is None and not os.environ.get("RAY_ADDRESS"):
        kwargs.update(num_cpus=cpus or os.cpu_count() or 1, include_dashboard=False)
    else:
        kwargs["address"] = address
        check_address(address)
    try:
        ray.init(**kwargs)
    except ConnectionError as e:
        raise ConfigError(
            f"--address {address or os.environ.get('RAY_ADDRESS')}: no Ray cluster answers there "
            f"({e}); accepted: the address `ray start --head` printed, or auto"
        ) from None
    return True


def on_actors(
    actor_class: type,
    args: tuple,
    tasks: list,
    *,
    address: str | None,
    actors: int | None,
    name: Callable[[Any], str],
    again: str,
    max_restarts: int = 3,
    max_task_retries: int = 3,
    sized: Callable[[int], None] | None = None,
) -> Iterator[Any]:
    """Each task's result as it finishes, run by ``actor.run(task)`` on Ray actors of ``actor_class(*args)``:
    ``actors`` of them (default one per CPU of the cluster; never more than tasks), each restarted up to
    ``max_restarts`` times when its process dies and a task run again up to ``max_task_retries`` times;
    ``sized(n)`` is told how many. Joins the cluster at ``address`` (or starts a private one, shut down at the
    end); the actors are ended when the caller stops reading. ``name(task)`` names a failed task in its
    :class:`BackendError`, ``again`` says there what a user does then."""
    if not tasks:
        return
    ray = import_ray()
    started = connect(ray, address, actors)
    pool = []
    try:
        n = max(1, min(actors or int(ray.cluster_resources().get("CPU", 1)), len(tasks)))
        if sized is not None:
            sized(n)
        remote = ray.remote(num_cpus=1, max_restarts=max_restarts, max_task_retries=max_task_retries)(
            actor_class
        )
        pool = [remote.remote(*args) for _ in range(n)]
        yield from _dispatch(ray, pool, tasks, name=name, again=again)
    finally:
        for actor in pool:
            ray.kill(actor)
        if started:
            ray.shutdown()


def _dispatch(ray, pool: list, tasks: list, *, name: Callable[[Any], str], again: str) -> Iterator[Any]:
    """Hand ``tasks`` to the actors of ``pool`` (``actor.run(task)``) as they free up, a few queued on each, and
    yield each result as it finishes."""
    pending = list(reversed(tasks))
    in_flight: dict = {}

    def send(actor) -> None:
        task = pending.pop()
        in_flight[actor.run.remote(task)] = (actor, task)

    for _ in range(TASKS_IN_FLIGHT_PER_ACTOR):
        for actor in pool:
            if pending:
                send(actor)
    while in_flight:
        ready, _ = ray.wait(list(in_flight), num_returns=1)
        actor, task = in_flight.pop(ready[0])
        try:
            result = ray.get(ready[0])
        except (ray.exceptions.RayActorError, ray.exceptions.RayTaskError) as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise BackendError(
                f"{name(task)} failed on the Ray cluster after its retries: {first}; {again}"
            ) from e
        if pending:
            send(actor)
        yield result
