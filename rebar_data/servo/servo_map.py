"""``rebar servo map SUITE --out DIR``: where servoing holds, over the element's surface and its orientations.

Every cell of the suite's ``map`` (:mod:`rebar_data.servo.sweep`) runs one episode, in this process, on a pool
of local worker processes (``--workers``), or on Ray actors (``--backend ray``, as ``rebar dataset build``
does); a cell's row is the same either way. Each finished cell is kept in a record beside ``DIR``
(``.DIR.map-cells/``, :class:`rebar_data.resume.Steps`), so a run stopped by Ctrl-C, a kill or a power cut,
run again, picks up with the cells it had not finished; a changed suite runs its cells again.

The outputs (:mod:`rebar_data.servo.map_report`), written beside ``DIR`` and swapped in whole at the end:
``map.parquet`` and ``map.csv`` (one row a cell), ``map.md``, ``map.png`` (the converged share, iterations and
worst true lateral error drawn on the unrolled surface) and ``summary.json``.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path

from tqdm import tqdm

import rebar_data
from rebar_data.config import ConfigError
from rebar_data.outputs import OutputLock, mark_output, output_folder, remove_stale, replace_folder
from rebar_data.pipeline import load_pipeline
from rebar_data.ray_cluster import check_backend
from rebar_data.resume import STEPS_FILE, Steps, key_of
from rebar_data.servo.config import SuiteConfig, load_suite, resolve_path
from rebar_data.servo.sweep import (
    Cell,
    CellActor,
    CellRunner,
    init_cell_process,
    plan_cells,
    run_cell_in_process,
)
from rebar_data.workers import check_workers, spawned_pool_map

COMMAND = "rebar servo map"


class MapInterrupted(KeyboardInterrupt):
    """Ctrl-C during a map: the finished cells are kept; the message says how many and how to go on."""


def cells_record(out: Path) -> Path:
    """The record of finished cells of the map written to ``out``."""
    return out.parent / f".{out.name}.map-cells"


def run_map(
    suite_path: str | Path,
    out: str | Path,
    *,
    workers: int = 1,
    backend: str = "local",
    address: str | None = None,
    progress: bool = True,
) -> dict:
    """Run every cell of the suite's map not yet finished, then write the map to ``out``; the summary."""
    if backend not in ("local", "ray"):
        raise ConfigError(f"--backend {backend}: unknown; accepted: local or ray")
    check_backend(backend, address)
    check_workers(workers, backend=backend)
    out = output_folder(out, arg="--out", command=COMMAND, swapped=True)
    suite = load_suite(suite_path)
    if suite.map is None:
        raise ConfigError(
            f"{suite_path}: has no map section; accepted: a suite with `map:` (eval/map-paper.yaml is one)"
        )
    load_pipeline(resolve_path(suite.world.mesh_config, suite_path))  # checked whole before any work
    if backend == "ray":
        from rebar_data.ray_cluster import check_address, import_ray

        import_ray()
        check_address(address)
    cells = plan_cells(suite.map)
    t0 = time.perf_counter()
    with OutputLock(out, command=COMMAND):
        output_folder(out, arg="--out", command=COMMAND, swapped=True)  # again, under the lock
        remove_stale(out.parent, f".{out.name}.tmp-*")
        record = cells_record(out)
        steps = Steps(record / STEPS_FILE)
        keys = {c.index: cell_key(suite, c) for c in cells}
        todo = [c for c in cells if not steps.done(_name(c.index), keys[c.index])]
        if len(todo) < len(cells):
            print(f"{len(cells) - len(todo)} of {len(cells)} cells done before, reused", file=sys.stderr)
        bar = tqdm(
            total=len(cells), initial=len(cells) - len(todo), desc="map", unit="cell", disable=not progress
        )
        runs = (
            _local(suite_path, todo, workers)
            if backend == "local"
            else _ray(suite_path, todo, workers, address)
        )
        try:
            for row in runs:
                steps.keep(_name(row["index"]), keys[row["index"]], row)
                bar.update(1)
        except KeyboardInterrupt:
            runs.close()
            done = sum(steps.done(_name(c.index), keys[c.index]) for c in cells)
            raise MapInterrupted(
                f"interrupted: {done} of {len(cells)} cells done and kept in {record}; run the same command "
                "again to continue"
            ) from None
        finally:
            bar.close()
        rows = [steps.result(_name(c.index)) for c in cells]
        summary = _write(suite, rows, out, wall_s=time.perf_counter() - t0, workers=workers, backend=backend)
        shutil.rmtree(record, ignore_errors=True)
    return summary


def cell_key(suite: SuiteConfig, cell: Cell) -> str:
    """What a cell's row is computed from: the whole suite (its map, detector, world...) and the cell."""
    return key_of(suite.model_dump(mode="json"), asdict(cell), rebar_data.__version__)


def _name(index: int) -> str:
    """A cell's name in the record of finished cells."""
    return f"cell {index}"


def _local(suite_path, cells: list[Cell], workers: int) -> Iterator[dict]:
    if not cells:
        return
    n = min(workers, len(cells))
    if n == 1:
        runner = CellRunner(suite_path)
        try:
            for c in cells:
                yield runner.run(c)
        finally:
            runner.close()
        return
    # each worker keeps the scene of the turn it ran last (turns are outermost, cells are handed out in order)
    yield from spawned_pool_map(n, init_cell_process, (str(suite_path),), run_cell_in_process, cells)


def _ray(suite_path, cells: list[Cell], actors: int, address: str | None) -> Iterator[dict]:
    from rebar_data.ray_cluster import on_actors

    yield from on_actors(
        CellActor,
        (str(Path(suite_path).absolute()),),
        cells,
        address=address,
        actors=actors,
        name=lambda c: _name(c.index),
        again="the cells that finished are kept, run the same command again to continue",
    )


def _write(
    suite: SuiteConfig, rows: list[dict], out: Path, *, wall_s: float, workers: int, backend: str
) -> dict:
    from rebar_data.servo.map_report import write_map

    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.tmp-") as tmp:
        folder = Path(tmp) / "map"
        folder.mkdir()
        summary = write_map(suite, rows, folder, wall_s=wall_s, workers=workers, backend=backend)
        mark_output(folder, COMMAND)
        replace_folder(folder, out)
    return summary
