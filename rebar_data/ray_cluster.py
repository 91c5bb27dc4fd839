"""Ray for the commands that spread independent work over a cluster (``dataset build --backend ray``,
``servo map --backend ray``): Ray itself or one clear message, joining or starting a cluster, and handing
tasks to long-lived actors as they free up.

Ray is imported only here and only when asked, so nothing else needs it installed.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Callable, Iterator

from rebar_data.config import ConfigError

RAY_INSTALL_HINT = "pip install -e '.[ray]' (or pip install 'ray>=2.30,<3')"
TASKS_IN_FLIGHT_PER_ACTOR = 2  # one running, one queued, so an actor never waits for the driver


class BackendError(RuntimeError):
    """A task failed on the cluster after Ray's retries; what finished is kept for the command to resume."""


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


def check_address(address: str | None) -> None:
    """One clear ConfigError when the cluster to join (``address``, else ``RAY_ADDRESS``) does not answer."""
    address = address or os.environ.get("RAY_ADDRESS", "")
    if address and not answers(address):
        raise ConfigError(
            f"--address {address}: no Ray cluster answers there; accepted: the HOST:PORT that "
            "`ray start --head` printed, or auto on a node of a running cluster"
        )


def connect(ray, address: str | None, cpus: int | None) -> bool:
    """Join the cluster at ``address`` (or ``RAY_ADDRESS``), else start a private one of ``cpus`` CPUs (the
    machine's by default); True when this call started it (and so must shut it down)."""
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


def dispatch(
    ray, pool: list, tasks: list, *, name: Callable[[object], str], after_failure: str
) -> Iterator[object]:
    """Hand tasks to the actors' ``run`` as they free up (a few queued per actor) and yield each result as it
    finishes. A task that still fails after Ray's retries is a BackendError naming it (``name(task)``) and
    saying ``after_failure`` (how to continue)."""
    pending = list(reversed(tasks))
    in_flight: dict = {}

    def submit(actor) -> None:
        task = pending.pop()
        in_flight[actor.run.remote(task)] = (actor, task)

    for _ in range(TASKS_IN_FLIGHT_PER_ACTOR):
        for actor in pool:
            if pending:
                submit(actor)
    while in_flight:
        ready, _ = ray.wait(list(in_flight), num_returns=1)
        actor, task = in_flight.pop(ready[0])
        try:
            result = ray.get(ready[0])
        except (ray.exceptions.RayActorError, ray.exceptions.RayTaskError) as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise BackendError(
                f"{name(task)} failed on the Ray cluster after its retries: {first}; {after_failure}"
            ) from e
        if pending:
            submit(actor)
        yield result
