"""`rebar dataset build` as users try it: never loses data, tells a live build from an interrupted one,
refuses bad values in one line, and prints clean output (also when interrupted)."""

from __future__ import annotations

import copy
import json
import os
import re
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from rebar_data.cli import main
from rebar_data.dataset import build as build_mod
from rebar_data.dataset import layout
from rebar_data.dataset.build import LocalRunner, build_dataset
from rebar_data.dataset.validate import validate_dataset
from rebar_data.outputs import OutputLock
from tests.dataset.conftest import TINY, write_config

ROOT = Path(__file__).resolve().parents[2]
REBAR = str(ROOT / ".venv" / "bin" / "rebar")
FILAMENT_CHATTER = ("FEngine", "EGL(", "OpenGL(", "CircularBuffer", "Open3D INFO")


class Recorder:
    """The local backend with one worker, keeping every shard's records."""

    label = "1 worker"

    def __init__(self):
        self.records: dict = {}

    def __call__(self, cfg, rm, staging, tasks):
        for tid, records in LocalRunner(1)(cfg, rm, staging, tasks):
            self.records[tid] = records
            yield tid, records


class Replay:
    """A runner that renders nothing: it copies a recorded build's files and hands back its records,
    optionally after waiting for ``release`` (a build that stays live as long as a test needs)."""

    label = "1 worker"

    def __init__(self, source: Path, records: dict, *, gated: bool = False):
        self.source, self.records, self.gated = source, records, gated
        self.started, self.release = threading.Event(), threading.Event()

    def __call__(self, cfg, rm, staging, tasks):
        self.started.set()
        if self.gated:
            assert self.release.wait(120)
        for tid, _, samples in tasks:
            for s in samples:
                for rel in (
                    layout.image_path(s.split, s.image_id),
                    layout.depth_path(s.split, s.image_id),
                    layout.sensor_depth_path(s.split, s.image_id),
                    layout.instance_path(s.split, s.image_id),
                ):
                    if (self.source / rel).exists():
                        (staging / rel).parent.mkdir(parents=True, exist_ok=True)
                        shutil.copyfile(self.source / rel, staging / rel)
            yield tid, self.records[tid]


@pytest.fixture(scope="module")
def recorded(tiny_config, tmp_path_factory):
    """One real build of the tiny pipeline: its dataset folder and every shard's records."""
    rec = Recorder()
    ds = build_dataset(tiny_config, tmp_path_factory.mktemp("recorded"), runner=rec)
    return ds, rec.records


def _errors(capsys) -> list[str]:
    return [x for x in capsys.readouterr().err.splitlines() if x.strip() and "%|" not in x]


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _build(config, out, *extra: str) -> list[str]:
    return ["dataset", "build", str(config), "--out", str(out), *extra]


# --- 1. --force: swap in, and only over this command's own dataset -------------------------------------


def test_force_swaps_the_new_dataset_in_so_the_path_always_holds_one(
    recorded, tiny_config, tmp_path, monkeypatch
):
    source, records = recorded
    final = tmp_path / "tiny" / "v0.0.1"
    shutil.copytree(source, final)
    (final / "from-the-old-build").write_text("old")
    real_rmtree = shutil.rmtree
    after_each_delete = []

    def watched_rmtree(path, *args, **kwargs):
        real_rmtree(path, *args, **kwargs)
        after_each_delete.append((str(path), (final / layout.INFO).exists()))

    monkeypatch.setattr(shutil, "rmtree", watched_rmtree)
    out = build_dataset(tiny_config, tmp_path, force=True, runner=Replay(source, records))
    assert out == final.resolve()
    assert after_each_delete and all(present for _, present in after_each_delete), after_each_delete
    assert not (final / "from-the-old-build").exists()
    assert validate_dataset(final) == []
    assert sorted(p.name for p in final.parent.iterdir()) == ["v0.0.1"]  # no .old, .partial or lock left


def test_force_refuses_a_folder_this_command_did_not_write(recorded, tiny_config, tmp_path, capsys):
    users = tmp_path / "tiny" / "v0.0.1"
    users.mkdir(parents=True)
    for i in range(3):
        (users / f"notes-{i}.txt").write_text(f"the user's own file {i}\n")
    before = _files(users)
    assert main(_build(tiny_config, tmp_path, "--workers", "1", "--force")) == 2
    err = _errors(capsys)
    assert len(err) == 1 and "did not write" in err[0] and str(users.resolve()) in err[0], err
    assert _files(users) == before
    assert main(_build(tiny_config, tmp_path, "--workers", "1")) == 2  # without --force: the same line
    err = _errors(capsys)
    assert len(err) == 1 and "did not write" in err[0], err
    # a dataset, but of another version, is not this build's either
    other = tmp_path / "other"
    shutil.copytree(recorded[0], other / "tiny" / "v0.0.1")
    info = json.loads((other / "tiny/v0.0.1" / layout.INFO).read_text())
    (other / "tiny/v0.0.1" / layout.INFO).write_text(json.dumps({**info, "version": "9.9.9"}))
    before = _files(other)
    assert main(_build(tiny_config, other, "--workers", "1", "--force")) == 2
    assert len(err := _errors(capsys)) == 1 and "did not write" in err[0], err
    assert _files(other) == before


def test_a_build_stopped_while_writing_its_files_still_resumes(recorded, tiny_config, tmp_path, monkeypatch):
    source, records = recorded
    real_manifest = build_mod.write_manifest

    def stopped(root):
        monkeypatch.setattr(build_mod, "write_manifest", real_manifest)
        raise KeyboardInterrupt

    monkeypatch.setattr(build_mod, "write_manifest", stopped)
    with pytest.raises(KeyboardInterrupt, match="`--resume` finishes it"):
        build_dataset(tiny_config, tmp_path, runner=Replay(source, records))
    final = tmp_path / "tiny" / "v0.0.1"
    assert not final.exists()
    out = build_dataset(tiny_config, tmp_path, resume=True, runner=Replay(source, records))
    assert validate_dataset(out) == []
    assert sorted(p.name for p in final.parent.iterdir()) == ["v0.0.1"]


# --- 2. one writer at a time -----------------------------------------------------------------------------


def test_a_live_build_is_told_apart_from_an_interrupted_one(recorded, tiny_config, tmp_path, capsys):
    source, records = recorded
    runner = Replay(source, records, gated=True)
    result: list = []

    def first_build():
        try:
            result.append(build_dataset(tiny_config, tmp_path, runner=runner))
        except BaseException as e:  # noqa: BLE001 - reported by the test
            result.append(e)

    live = threading.Thread(target=first_build)
    live.start()
    try:
        assert runner.started.wait(60)  # the first build has its staging folder and is rendering
        capsys.readouterr()
        for extra in ((), ("--resume",), ("--force",)):
            assert main(_build(tiny_config, tmp_path, "--workers", "1", *extra)) == 2, extra
            err = _errors(capsys)
            assert len(err) == 1, (extra, err)
            assert f"(pid {os.getpid()}) is writing there now" in err[0], (extra, err)
    finally:
        runner.release.set()
        live.join(120)
    final = tmp_path / "tiny" / "v0.0.1"
    assert result == [final.resolve()]
    assert validate_dataset(final) == []
    assert sorted(p.name for p in final.parent.iterdir()) == ["v0.0.1"]


def test_an_interrupted_build_is_named_only_when_no_one_holds_the_lock(tiny_config, tmp_path, capsys):
    staging = tmp_path / "tiny" / ".v0.0.1.partial"
    staging.mkdir(parents=True)
    (staging / "plan.json").write_text(json.dumps({"config_hash": "as a build left it"}))
    with OutputLock(tmp_path / "tiny" / "v0.0.1", command="rebar dataset build"):
        assert main(_build(tiny_config, tmp_path, "--workers", "1")) == 2
        err = _errors(capsys)
        assert len(err) == 1 and "is writing there now" in err[0] and "an interrupted build" not in err[0], (
            err
        )
    assert main(_build(tiny_config, tmp_path, "--workers", "1")) == 2
    err = _errors(capsys)
    assert len(err) == 1 and f"an interrupted build is at {staging.resolve()}" in err[0], err


def test_the_ray_backend_takes_the_lock_on_the_driver(tiny_config, tmp_path, capsys):
    pytest.importorskip("ray")
    with OutputLock(tmp_path / "tiny" / "v0.0.1", command="rebar dataset build"):
        assert main(_build(tiny_config, tmp_path, "--backend", "ray", "--workers", "1")) == 2
    err = _errors(capsys)
    assert len(err) == 1 and f"(pid {os.getpid()}) is writing there now" in err[0], err


# --- 3. unusable paths: one line, before any work ------------------------------------------------------


def test_a_binary_pipeline_is_one_line(tmp_path, capsys):
    binary = tmp_path / "pipeline.yaml"
    binary.write_bytes(bytes(range(256)) * 64)
    assert main(_build(binary, tmp_path / "out")) == 2
    err = _errors(capsys)
    assert len(err) == 1 and "not a text file" in err[0] and str(binary) in err[0], err
    assert not (tmp_path / "out").exists()


def test_out_that_is_a_file_is_one_line(tiny_config, tmp_path, capsys):
    f = tmp_path / "out.txt"
    f.write_text("the user's file\n")
    assert main(_build(tiny_config, f)) == 2
    err = _errors(capsys)
    assert len(err) == 1 and "--out" in err[0] and "is a file" in err[0], err
    assert f.read_text() == "the user's file\n"
    (tmp_path / "root").mkdir()
    (tmp_path / "root" / "tiny").write_text("a file where the dataset's name folder goes\n")
    assert main(_build(tiny_config, tmp_path / "root")) == 2
    err = _errors(capsys)
    assert len(err) == 1 and "is a file" in err[0], err


def test_a_read_only_out_is_one_line(tiny_config, tmp_path, capsys, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    if os.geteuid() == 0:  # root may write anywhere: let os.access answer as it would for the folder's owner
        real_access = os.access

        def access_by_mode_bits(path, mode, *args, **kwargs):
            if mode & os.W_OK and Path(path).exists() and not os.stat(path).st_mode & stat.S_IWUSR:
                return False
            return real_access(path, mode, *args, **kwargs)

        monkeypatch.setattr(os, "access", access_by_mode_bits)
    try:
        assert main(_build(tiny_config, ro / "data", "--workers", "1")) == 2
        err = _errors(capsys)
        assert len(err) == 1 and "not writable" in err[0] and "--out" in err[0], err
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o755)


# --- 5. --workers within bounds ------------------------------------------------------------------------


@pytest.mark.parametrize("workers", ["-1", "0", str((os.cpu_count() or 1) + 1)])
def test_workers_out_of_range_is_refused_with_the_range(workers, tiny_config, tmp_path, capsys):
    assert main(_build(tiny_config, tmp_path, "--workers", workers)) == 2
    err = _errors(capsys)
    assert len(err) == 1 and f"--workers {workers}" in err[0] and f"1 to {os.cpu_count()}" in err[0], err
    assert not (tmp_path / "tiny").exists()


def test_ray_actors_must_be_one_or_more(tiny_config, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # the bound is checked before Ray is looked for
    assert main(_build(tiny_config, tmp_path, "--backend", "ray", "--workers", "0")) == 2
    err = _errors(capsys)
    assert len(err) == 1 and "--workers 0" in err[0] and "1 or more" in err[0], err


def test_the_help_states_the_bounds(capsys):
    with pytest.raises(SystemExit):
        main(["dataset", "build", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert f"1 to {os.cpu_count()}" in text and "two cores" in text and "1 or more" in text


def test_one_worker_is_singular(tiny_config, tmp_path, capsys):
    assert main(_build(tiny_config, tmp_path, "--workers", "1")) == 0
    err = capsys.readouterr().err
    assert "with 1 worker)" in err and "1 workers" not in err, err[-300:]


# --- 4 and 6. Ctrl-C and kill -9 from a real terminal; no renderer chatter -------------------------------

MANY = copy.deepcopy(TINY) | {"name": "many"}
MANY["camera"] = {
    **TINY["camera"],
    "trajectories": [
        {"kind": "orbit_arc", "count": 10, "frames": 4, "edge_margin_m": 0.1},
        {"kind": "straight_pass", "count": 10, "frames": 4, "edge_margin_m": 0.1},
    ],
}


def _env() -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XDG_RUNTIME_DIR"}
    return env | {"EGL_PLATFORM": "surfaceless"}


def _wait_for_records(records: Path, more_than: int, proc: subprocess.Popen, timeout_s: float = 240) -> int:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        n = len(list(records.glob("*.pkl")))
        if n > more_than:
            return n
        time.sleep(0.05)
    raise AssertionError(f"no record beyond {more_than} was saved (exit {proc.poll()})")


def _default_sigint() -> None:
    """In a child before it runs: Ctrl-C's default action, whatever this process inherited."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    kids = []
    for stat_file in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat_file.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid:
            kids.append(int(stat_file.parent.name))
    return kids


def _chatter(text: str) -> list[str]:
    return [x for x in text.splitlines() if "error:" in x or any(c in x for c in FILAMENT_CHATTER)]


def test_ctrl_c_and_kill_9_leave_a_build_that_resumes(tmp_path):
    config = write_config(tmp_path / "cfg", MANY, "many.yaml")
    out = tmp_path / "out"
    final, staging = out / "many" / "v0.0.1", out / "many" / ".v0.0.1.partial"
    cmd = [REBAR, *_build(config, out, "--workers", "2")]
    # kill -9 of the build's process: its workers lose their parent and end
    first = subprocess.Popen(
        cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True
    )
    n = _wait_for_records(staging / "records", 0, first)
    first.kill()
    first.communicate(timeout=60)
    # Ctrl-C in a terminal: SIGINT to the whole process group. The build starts with Ctrl-C's default action,
    # as from a terminal: a shell without job control starts its background jobs (`cmd &`, `nohup`) with
    # SIGINT ignored, and a test run started that way would pass that on and see no interrupt at all
    second = subprocess.Popen(
        [*cmd, "--resume"], env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True, preexec_fn=_default_sigint,
    )  # fmt: skip
    n = _wait_for_records(staging / "records", n, second)
    for worker in _children(second.pid):  # a Ctrl-C that reaches the workers alone changes nothing
        os.kill(worker, signal.SIGINT)
    _wait_for_records(staging / "records", n, second)
    os.killpg(second.pid, signal.SIGINT)
    stdout, stderr = second.communicate(timeout=120)
    lines = [x for x in stderr.splitlines() if x.strip() and "%|" not in x]
    assert "Traceback" not in stderr + stdout, stderr[-2000:]
    assert second.returncode == 130, stderr[-2000:]
    assert len(lines) == 1 and re.fullmatch(
        r"interrupted after \d+ of 80 images; `--resume` continues it", lines[0]
    ), lines
    assert staging.is_dir() and not final.exists()
    third = subprocess.run([*cmd, "--resume"], env=_env(), capture_output=True, text=True, timeout=300)
    assert third.returncode == 0, third.stderr[-2000:]
    assert third.stdout.strip().splitlines() == [str(final.resolve())]
    assert _chatter(third.stdout + third.stderr) == []
    assert validate_dataset(final) == []
    ids = pq.read_table(final / layout.SAMPLES).column("image_id").to_pylist()
    assert len(ids) == len(set(ids)) == 80
    assert sorted(p.name for p in final.parent.iterdir()) == ["v0.0.1"]


RENDER_ONE_FRAME = """
import numpy as np
from rebar_data.pipeline import load_pipeline
from rebar_data.dataset.plan import make_plan
from rebar_data.geometry.build import build_rebar_mesh
from rebar_data.render.renderer import Renderer
from rebar_data.scene.cameras import intrinsics_from_config
from rebar_data.scene.sample import sample_sensor

cfg = load_pipeline({config!r})
rm = build_rebar_mesh(cfg.mesh_config())
plan = make_plan(cfg, rm)
rng = np.random.default_rng(0)
with Renderer(intrinsics_from_config(cfg.camera), cfg.render) as r:
    r.set_mesh(rm)
    r.set_scene(plan.scenes[0])
    frame = r.render(plan.samples[0].world_from_camera, sample_sensor(cfg.scene, rng), rng)
print("rendered", frame.rgb.shape, flush=True)
"""


def test_rendering_a_frame_prints_no_renderer_chatter(tiny_config):
    script = RENDER_ONE_FRAME.format(config=str(tiny_config))
    p = subprocess.run(
        [sys.executable, "-c", script], env=_env(), capture_output=True, text=True, timeout=300, cwd=ROOT
    )
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.strip() == "rendered (120, 160, 3)", p.stdout
    assert _chatter(p.stdout + p.stderr) == [], p.stdout + p.stderr
    assert p.stderr.strip() == "", p.stderr
