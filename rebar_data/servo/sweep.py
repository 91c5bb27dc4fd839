"""The cells of a servo map and the episode each one runs (``rebar servo map``; the map's config is
:class:`rebar_data.servo.config.MapConfig`).

A cell is a mode, a turn of the element about its own normal at the crown, a camera view and a point of the
element's surface (axial and arc distances from the crown). Its episode starts with the camera looking at that
point from the map's standoff, in that view, and visits the map's ``targets`` crossings nearest the image
centre. Each cell's episode draws from its own seed (the suite's seed and the cell's index), and its context is
built from the suite alone, so a cell gives the same row in any process: one worker, many, or a Ray actor.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rebar_data.servo.config import EpisodeSpec, MapConfig, StartPose, SuiteConfig, load_suite
from rebar_data.servo.context import ServoContext
from rebar_data.servo.recorder import Recorder
from rebar_data.workers import renderer_process

MAP_EPISODE_OFFSET = 3000  # a map cell's episode index (seed and rows): 3000 + the cell's index


@dataclass(frozen=True)
class Cell:
    """One cell of a map; ``view`` indexes the map's ``views``."""

    index: int
    mode: str
    turn_deg: float
    view: int
    axial_m: float
    arc_m: float


def _grid(lo: float, hi: float, steps: int) -> list[float]:
    return [0.5 * (lo + hi)] if steps == 1 else [float(x) for x in np.linspace(lo, hi, steps)]


def plan_cells(m: MapConfig) -> list[Cell]:
    """Every cell, turns outermost (a worker then builds each turn's scene once, as cells come in order)."""
    cells = []
    for turn in m.turns_deg:
        for mode in m.modes:
            for view in range(len(m.views)):
                for a in _grid(*m.axial_m, m.axial_steps):
                    for s in _grid(*m.arc_m, m.arc_steps):
                        cells.append(Cell(len(cells), mode, float(turn), view, round(a, 6), round(s, 6)))
    return cells


def turned(suite: SuiteConfig, turn_deg: float) -> SuiteConfig:
    """The suite with its element turned by ``turn_deg`` about the element's own z axis (its normal at the
    crown); the crown stays where it is."""
    if turn_deg == 0.0:
        return suite
    R = Rotation.from_euler("xyz", suite.world.mesh_rotation_deg, degrees=True)
    with warnings.catch_warnings():
        # at a gimbal lock scipy picks one of the equal angle triples: the same rotation either way
        warnings.simplefilter("ignore", UserWarning)
        rot = (R * Rotation.from_euler("z", turn_deg, degrees=True)).as_euler("xyz", degrees=True)
    world = suite.world.model_copy(update={"mesh_rotation_deg": tuple(float(x) for x in rot)})
    return suite.model_copy(update={"world": world})


NAN = float("nan")


def _worst(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return max(finite) if finite else NAN


class CellRunner:
    """Runs cells in one process, one context (renderer and simulator) at a time: the renderer is one per
    process, so a cell of another turn closes the context and builds that turn's."""

    def __init__(self, suite_path: str | Path):
        os.environ.setdefault("EGL_PLATFORM", "surfaceless")
        self.suite_path = str(suite_path)
        self.suite = load_suite(suite_path)
        if self.suite.map is None:
            raise ValueError(f"{suite_path}: no map section")
        self.map: MapConfig = self.suite.map
        self.ctx: ServoContext | None = None
        self.turn: float | None = None

    def _context(self, turn_deg: float) -> ServoContext:
        from rebar_data.servo.run import build_context

        if self.ctx is None or self.turn != turn_deg:
            self.close()
            self.ctx = build_context(turned(self.suite, turn_deg), self.suite_path)
            self.turn = turn_deg
        return self.ctx

    def run(self, cell: Cell) -> dict:
        """The cell's row: where it started, whether the arm reached that start, and how its visits ended
        (``converged``: every visit converged; errors are the worst over the visits, from the simulator)."""
        from rebar_data.servo.episode import EpisodeRunner

        t0 = time.perf_counter()
        ctx = self._context(cell.turn_deg)
        view = self.map.views[cell.view]
        start = StartPose(
            look_at_m=(cell.axial_m, cell.arc_m),
            standoff_m=self.map.standoff_m,
            tilt_deg=view.tilt_deg,
            roll_deg=view.roll_deg,
        )
        row = {
            **asdict(cell),
            "tilt_x_deg": float(view.tilt_deg[0]),
            "tilt_y_deg": float(view.tilt_deg[1]),
            "roll_deg": float(view.roll_deg),
        }
        world = ctx.world
        if self.map.base == "follow":
            world.move_base(
                world.surface_point(cell.axial_m, cell.arc_m)[0] - world.surface_point(0.0, 0.0)[0]
            )
        try:
            q, ok = world.solve_start(world.camera_pose_for(start))
            if not (ok and world.clear_at(q)):  # out of reach, or a link in the mesh, the table or the floor
                return row | _outcome("unreachable", reachable=False, wall_s=time.perf_counter() - t0)
            index = MAP_EPISODE_OFFSET + cell.index
            spec = EpisodeSpec(mode=cell.mode, start=start, targets=self.map.targets, choice="nearest")
            seq = np.random.SeedSequence([self.suite.seed, index, 7])
            visits = EpisodeRunner(ctx, spec, index, seq, Recorder()).run(start, q).visits
        finally:
            world.move_base(np.zeros(3))
        reasons = [v.reason for v in visits]
        failed = [r for r in reasons if r != "converged"]
        done = [v for v in visits if v.converged]
        return row | _outcome(
            failed[0] if failed else "converged",
            reachable=True,
            wall_s=time.perf_counter() - t0,
            visits=len([v for v in visits if v.reason != "no_target"]),
            converged_visits=len(done),
            iterations=float(np.median([v.iterations for v in done])) if done else NAN,
            lateral_error_m=_worst([v.final_true_lateral_error_m for v in done]),
            tilt_error_deg=_worst([v.final_tilt_error_deg for v in done]),
            jaw_error_deg=_worst([v.final_jaw_error_deg for v in done]),
            tied=sum(bool(v.tied) for v in visits),
            sim_s=float(sum(v.sim_s for v in visits)),
        )

    def close(self) -> None:
        if self.ctx is not None:
            self.ctx.close()
            self.ctx, self.turn = None, None


def _outcome(reason: str, *, reachable: bool, wall_s: float, **values) -> dict:
    row = {
        "reachable": reachable,
        "reason": reason,
        "converged": reason == "converged",
        "visits": 0,
        "converged_visits": 0,
        "iterations": NAN,
        "lateral_error_m": NAN,
        "tilt_error_deg": NAN,
        "jaw_error_deg": NAN,
        "tied": 0,
        "sim_s": 0.0,
    }
    row.update(values)
    row["wall_s"] = float(wall_s)
    return row


# --- worker processes: one CellRunner each (the local pool's initializer; a Ray actor wraps the class) ---
_RUNNER: CellRunner | None = None


def init_cell_process(suite_path: str) -> None:
    global _RUNNER
    renderer_process()  # the parent answers Ctrl-C and ends the pool
    _RUNNER = CellRunner(suite_path)


def run_cell_in_process(cell: Cell) -> dict:
    assert _RUNNER is not None
    return _RUNNER.run(cell)


class CellActor:
    """A Ray actor's cell runner (wrapped by ``ray.remote``)."""

    def __init__(self, suite_path: str):
        renderer_process(answers_ctrl_c=True)
        self.runner = CellRunner(suite_path)

    def run(self, cell: Cell) -> dict:
        return self.runner.run(cell)
