"""What a command may write: path arguments, ownership, the swap, the one-writer lock."""

from __future__ import annotations

import multiprocessing as mp
import os

import pytest

from rebar_data.config import ConfigError
from rebar_data.outputs import (
    OutputLock,
    input_file,
    input_folder,
    mark_output,
    output_file,
    output_folder,
    outside_inputs,
    replace_folder,
    restore_interrupted_swap,
)


def test_input_file_refuses_each_unusable_path(tmp_path):
    with pytest.raises(ConfigError, match="--cfg .*no such file"):
        input_file(tmp_path / "nope.yaml", arg="--cfg", what="a YAML file")
    with pytest.raises(ConfigError, match="is a folder"):
        input_file(tmp_path, arg="--cfg", what="a YAML file")
    binary = tmp_path / "b.yaml"
    binary.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(ConfigError, match="not a text file"):
        input_file(binary, arg="--cfg", what="a YAML file", text=True)
    text = tmp_path / "t.yaml"
    text.write_text("name: é\n")
    assert input_file(text, arg="--cfg", what="a YAML file", text=True) == text


def test_input_folder_refuses_a_file(tmp_path):
    f = tmp_path / "f"
    f.write_text("x")
    with pytest.raises(ConfigError, match="is a file"):
        input_folder(f, arg="DATASET", what="a dataset folder")


def test_output_folder_refuses_what_the_command_did_not_write(tmp_path):
    user = tmp_path / "user"
    user.mkdir()
    (user / "thesis.tex").write_text("years of work")
    with pytest.raises(ConfigError, match="did not write"):
        output_folder(user, arg="--out", command="rebar servo run")
    mark_output(user, "rebar servo run")
    assert output_folder(user, arg="--out", command="rebar servo run") == user
    with pytest.raises(ConfigError, match="did not write"):
        output_folder(user, arg="--out", command="rebar dataset publish")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert output_folder(empty, arg="--out", command="rebar servo run") == empty
    assert output_folder(tmp_path / "new" / "deeper", arg="--out", command="x") == tmp_path / "new" / "deeper"


def test_output_folder_refuses_a_file_and_an_unwritable_place(tmp_path):
    f = tmp_path / "f"
    f.write_text("x")
    with pytest.raises(ConfigError, match="is a file"):
        output_folder(f, arg="--out", command="x")
    with pytest.raises(ConfigError, match="is a file"):
        output_folder(f / "sub", arg="--out", command="x")
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        with pytest.raises(ConfigError, match="not writable"):
            output_folder(ro / "run", arg="--out", command="x")


def test_output_file_and_outside_inputs(tmp_path):
    with pytest.raises(ConfigError, match="is a folder"):
        output_file(tmp_path, arg="--out", what="a .parquet file")
    existing = tmp_path / "p.parquet"
    existing.write_text("not ours")
    with pytest.raises(ConfigError, match="did not write"):
        output_file(existing, arg="--out", what="a .parquet file", owned=lambda p: False)
    assert output_file(existing, arg="--out", what="a .parquet file", owned=lambda p: True) == existing
    photos = tmp_path / "photos"
    photos.mkdir()
    with pytest.raises(ConfigError, match="lies in the input"):
        outside_inputs(photos, [photos], arg="--out")
    with pytest.raises(ConfigError, match="lies in the input"):
        outside_inputs(photos / "overlays", [photos], arg="--out")
    outside_inputs(tmp_path / "overlays", [photos], arg="--out")


def test_replace_folder_swaps_whole_folders(tmp_path):
    final, staging = tmp_path / "v1", tmp_path / ".v1.partial"
    final.mkdir()
    (final / "old").write_text("old")
    staging.mkdir()
    (staging / "new").write_text("new")
    replace_folder(staging, final)
    assert sorted(p.name for p in final.iterdir()) == ["new"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v1"]


def test_a_swap_cut_between_its_renames_is_put_back(tmp_path):
    final = tmp_path / "v1"
    old = tmp_path / ".v1.old"
    old.mkdir()
    (old / "data").write_text("the old dataset")
    restore_interrupted_swap(final)
    assert (final / "data").read_text() == "the old dataset"


def _hold(target, started, release):
    with OutputLock(target, command="rebar dataset build"):
        started.set()
        release.wait(30)


def test_the_lock_tells_a_live_writer_from_a_dead_one(tmp_path):
    target = tmp_path / "v1"
    ctx = mp.get_context("spawn")
    started, release = ctx.Event(), ctx.Event()
    p = ctx.Process(target=_hold, args=(target, started, release))
    p.start()
    try:
        assert started.wait(60)
        holder = OutputLock.held_by(target)
        assert holder == {"pid": p.pid, "command": "rebar dataset build"}
        busy = rf"rebar dataset build` \(pid {p.pid}\) is writing there now"
        with pytest.raises(ConfigError, match=busy), OutputLock(target, command="rebar dataset build"):
            pass
    finally:
        release.set()
        p.join(30)
    assert OutputLock.held_by(target) is None
    with OutputLock(target, command="x"):
        assert OutputLock.held_by(target) == {"pid": os.getpid(), "command": "x"}  # flock is per open file
    assert not (tmp_path / ".v1.lock").exists()


def test_a_killed_writer_leaves_no_lock(tmp_path):
    target = tmp_path / "v1"
    ctx = mp.get_context("spawn")
    started, release = ctx.Event(), ctx.Event()
    p = ctx.Process(target=_hold, args=(target, started, release))
    p.start()
    assert started.wait(60)
    p.kill()
    p.join(30)
    assert (tmp_path / ".v1.lock").exists()  # the file stays, the lock does not
    assert OutputLock.held_by(target) is None
    with OutputLock(target, command="x"):
        pass
