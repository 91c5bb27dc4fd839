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


# --- symbolic links, full disks, copies and temporary folders -----------------------------------------


def test_a_symbolic_link_as_out_is_refused_and_kept(tmp_path):
    target = tmp_path / "target"
    target.mkdir()
    (target / "theirs.txt").write_text("the user's")
    link = tmp_path / "link"
    link.symlink_to(target)
    with pytest.raises(ConfigError, match=r"--out .*link: is a symbolic link \(to .*target\).*accepted"):
        output_folder(link, arg="--out", command="rebar x")
    file_link = tmp_path / "out.parquet"
    file_link.symlink_to(target / "theirs.txt")
    with pytest.raises(ConfigError, match="is a symbolic link"):
        output_file(file_link, arg="--out", what="a Parquet file")
    staging = tmp_path / "staging"
    staging.mkdir()
    with pytest.raises(ConfigError, match="is a symbolic link"):
        replace_folder(staging, link)
    assert link.is_symlink() and (target / "theirs.txt").read_text() == "the user's" and staging.is_dir()


def test_a_full_disk_is_one_line_naming_the_folder_and_the_space(tmp_path):
    import errno

    from rebar_data.outputs import space_for

    with pytest.raises(ConfigError) as e, space_for(tmp_path / "out", lambda: 12_345_678):
        raise OSError(errno.ENOSPC, "No space left on device")
    msg = str(e.value)
    assert "\n" not in msg and str(tmp_path / "out") in msg and "no space left" in msg, msg
    assert "free)" in msg and "needs about 12.3 MB" in msg, msg
    with pytest.raises(OSError, match="other"), space_for(tmp_path, lambda: 1):
        raise OSError(errno.EIO, "other")  # any other failure is not a full disk


def test_a_copy_is_its_own_file(tmp_path):
    from rebar_data.outputs import copy_file

    src = tmp_path / "a.png"
    src.write_bytes(b"\x89PNG the dataset's image" * 1000)
    os.utime(src, (1_000_000_000, 1_000_000_000))
    dst = tmp_path / "bundle" / "a.png"
    copy_file(src, dst)
    assert dst.read_bytes() == src.read_bytes() and dst.stat().st_mtime == 1_000_000_000
    assert dst.stat().st_ino != src.stat().st_ino and src.stat().st_nlink == 1
    dst.write_bytes(b"re-saved in an image editor")
    assert src.read_bytes().startswith(b"\x89PNG the dataset's image")


def test_a_dead_process_temporary_folder_is_removed(tmp_path, monkeypatch):
    import subprocess
    import sys
    import tempfile

    from rebar_data.outputs import private_temp_dir, remove_stale

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    )
    stale = tmp_path / f"rebar-runtime-{int(dead.stdout)}-abc"
    stale.mkdir()
    live = tmp_path / f"rebar-runtime-{os.getpid()}-def"  # this process's: alive, kept
    live.mkdir()
    other = tmp_path / "rebar-runtime-notes"  # not one of ours
    other.mkdir()
    made = private_temp_dir("rebar-runtime-")
    assert made.is_dir() and made.name.startswith(f"rebar-runtime-{os.getpid()}-")
    assert not stale.exists() and live.is_dir() and other.is_dir()
    (tmp_path / ".bundle.partial-x1").mkdir()
    (tmp_path / ".bundle.partial-x1" / "half.parquet").write_bytes(b"PAR1")
    remove_stale(tmp_path, ".bundle.partial-*")
    assert not (tmp_path / ".bundle.partial-x1").exists()
