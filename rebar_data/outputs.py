"""Where commands read and write: path arguments checked before work starts, one writer per output, and
nothing replaced that the command did not provably write.

The rules every command follows:

- A path argument is checked before any work: missing, a file where a folder is wanted (or the other
  way), not readable, not writable, or binary where text is wanted, each is one ``ConfigError`` line
  naming the argument (exit status 2) and nothing is written.
- A command replaces or deletes an existing output only when it is provably that command's own: the
  folder carries the command's mark (``OWNER_FILE``, written by ``mark_output``) or a layout only that
  command writes (a caller's ``owned`` test). Anything else is the user's and is refused.
- Outputs never go into an input: ``outside_inputs`` refuses an output inside an input folder.
- Replacing is rename, swap, delete (``replace_folder``): a reader always finds a whole old or a whole
  new folder, never none.
- One writer at a time (``OutputLock``): an ``fcntl`` lock on a file beside the output. The operating
  system frees it when the holder dies, so a live writer is told apart from an interrupted one.
- An output that is a symbolic link is refused (the swap would replace the link, not write where it
  points); the folder it points to is accepted.
- A full disk is one line naming the folder, the space free and about how much the output needs
  (``space_for``); the writer removes what it had half-written.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from rebar_data.config import ConfigError

OWNER_FILE = ".rebar-output.json"
"""The mark a command leaves in a folder it wrote: ``{"command": ..., "created_at": ...}``."""


def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _refuse_link(path: Path, arg: str, what: str) -> None:
    """A symbolic link as an output: replacing the output would replace the link, so it is refused."""
    if path.is_symlink():
        target = Path(os.path.realpath(path))
        raise ConfigError(
            f"{arg} {path}: is a symbolic link (to {target}), which writing the output would replace; "
            f"accepted: the path it points to ({target}), or {what}"
        )


def _check_writable(path: Path, arg: str) -> None:
    """``path`` (which need not exist) can be created: its nearest existing ancestor is a writable folder."""
    base = _nearest_existing(path)
    if not base.is_dir():
        raise ConfigError(
            f"{arg} {path}: {base} is a file, so nothing can be made under it; accepted: a path in a folder"
        )
    if not os.access(base, os.W_OK | os.X_OK):
        raise ConfigError(f"{arg} {path}: {base} is not writable; accepted: a folder you may write to")


def input_file(path: str | Path, *, arg: str, what: str, text: bool = False) -> Path:
    """An input file that exists and is readable; with ``text``, one that decodes as UTF-8 text (looked at
    only in a regular file: a pipe such as ``<(...)`` can be read once, by the command that parses it)."""
    p = Path(path)
    if not p.exists():
        raise ConfigError(f"{arg} {p}: no such file; accepted: {what}")
    if p.is_dir():
        raise ConfigError(f"{arg} {p}: is a folder; accepted: {what}")
    if not os.access(p, os.R_OK):
        raise ConfigError(f"{arg} {p}: not readable; accepted: {what} you may read")
    if text and p.is_file():
        with open(p, "rb") as f:
            head = f.read(1 << 16)
        try:
            head.decode("utf-8")
        except UnicodeDecodeError as e:
            if e.start < len(head) - 4:  # a multi-byte character cut by the 64 KiB read is not binary
                raise ConfigError(f"{arg} {p}: not a text file; accepted: {what}") from None
        if b"\0" in head:
            raise ConfigError(f"{arg} {p}: not a text file; accepted: {what}")
    return p


def input_folder(path: str | Path, *, arg: str, what: str) -> Path:
    """An input folder that exists and is readable."""
    p = Path(path)
    if not p.exists():
        raise ConfigError(f"{arg} {p}: no such folder; accepted: {what}")
    if not p.is_dir():
        raise ConfigError(f"{arg} {p}: is a file; accepted: {what}")
    if not os.access(p, os.R_OK | os.X_OK):
        raise ConfigError(f"{arg} {p}: not readable; accepted: {what} you may read")
    return p


def outside_inputs(out: Path, inputs: Iterable[Path], *, arg: str) -> None:
    """Refuse an output that is, or lies inside, one of the input folders (or is an input file)."""
    o = Path(out).resolve()
    for i in inputs:
        r = Path(i).resolve()
        if o == r or (r.is_dir() and o.is_relative_to(r)):
            raise ConfigError(
                f"{arg} {out}: lies in the input {i}, whose files would be overwritten; accepted: a folder "
                "outside every input"
            )


def owned_by(folder: Path, command: str) -> bool:
    """True when ``folder`` carries ``command``'s mark."""
    mark = Path(folder) / OWNER_FILE
    try:
        return json.loads(mark.read_text()).get("command") == command
    except (OSError, ValueError, AttributeError):
        return False


def mark_output(folder: Path, command: str) -> None:
    """Leave ``command``'s mark in ``folder``, which it wrote (see ``owned_by``)."""
    record = {"command": command, "created_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    (Path(folder) / OWNER_FILE).write_text(json.dumps(record, sort_keys=True) + "\n")


def output_folder(
    path: str | Path,
    *,
    arg: str,
    command: str,
    owned: Callable[[Path], bool] | None = None,
    swapped: bool = False,
) -> Path:
    """An output folder ``command`` may write: new, empty, or provably its own earlier output.

    ``owned`` decides for a folder without the mark (a layout only this command writes); without it only
    ``OWNER_FILE`` does. ``swapped``: the folder is written beside it and swapped in (``replace_folder``),
    so the folder that holds it must be writable too. Nothing is created here.
    """
    p = Path(path)
    _refuse_link(p, arg, "a new folder")
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{arg} {p}: is a file; accepted: a new folder or an earlier `{command}` output")
    _check_writable(p, arg)
    if swapped and p.exists() and not os.access(p.absolute().parent, os.W_OK | os.X_OK):
        raise ConfigError(
            f"{arg} {p}: its folder {p.absolute().parent} is not writable, where the new output is made and "
            "swapped in; accepted: a folder in a place you may write to"
        )
    if p.is_dir():
        if not os.access(p, os.W_OK | os.X_OK):
            raise ConfigError(f"{arg} {p}: not writable; accepted: a folder you may write to")
        if any(p.iterdir()) and not owned_by(p, command) and not (owned and owned(p)):
            raise ConfigError(
                f"{arg} {p}: holds files that `{command}` did not write, and it would replace them; "
                f"accepted: a new or empty folder, or an earlier `{command}` output"
            )
    return p


def output_file(
    path: str | Path,
    *,
    arg: str,
    what: str,
    owned: Callable[[Path], bool] | None = None,
) -> Path:
    """An output file that may be written: new, or (with ``owned``) provably the command's earlier output.

    Without ``owned`` an existing file is replaced (the caller's output is a file a user names for it).
    """
    p = Path(path)
    _refuse_link(p, arg, "a new file")
    if p.is_dir():
        raise ConfigError(f"{arg} {p}: is a folder; accepted: {what}")
    _check_writable(p.parent, arg)
    if p.exists():
        if not os.access(p, os.W_OK):
            raise ConfigError(f"{arg} {p}: not writable; accepted: {what} you may write")
        if owned is not None and not owned(p):
            raise ConfigError(
                f"{arg} {p}: is a file this command did not write; accepted: a new file, {what}"
            )
    return p


def replace_file(path: Path, write: Callable[[Path], object]) -> Path:
    """``write(tmp)`` to a file beside ``path``, then rename it over ``path``: a reader finds the whole old file
    or the whole new one, and a failed write leaves no temporary file."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _old_of(final: Path) -> Path:
    return final.parent / f".{final.name}.old"


def restore_interrupted_swap(final: Path) -> None:
    """Undo a ``replace_folder`` that stopped between its two renames (the old folder put back)."""
    old = _old_of(final)
    if old.exists() and not final.exists():
        old.rename(final)


def replace_folder(staging: Path, final: Path) -> None:
    """Put ``staging`` at ``final``: rename the old one aside, rename the new one in, then delete the old.

    At every moment ``final`` is either the whole old folder or the whole new one (between the two renames,
    for an instant, neither; ``restore_interrupted_swap`` puts the old one back if the process dies there).
    """
    final = Path(final)
    old = _old_of(final)
    for p, what in ((final, "the output"), (old, "an earlier output set aside")):
        if p.is_symlink():  # never swapped away or deleted through: the link is the user's
            raise ConfigError(
                f"{p}: {what} is a symbolic link (to {os.path.realpath(p)}), which would be replaced; "
                "accepted: a real folder there (move the link away)"
            )
    restore_interrupted_swap(final)
    if old.exists():
        shutil.rmtree(old)
    if final.exists():
        final.rename(old)
    Path(staging).rename(final)
    if old.exists():
        shutil.rmtree(old)


NO_SPACE = (errno.ENOSPC, errno.EDQUOT)


def size_text(n_bytes: float) -> str:
    """``12.3 MB``: a size for a message (decimal units, as ``df -H`` shows them)."""
    for unit in ("B", "kB", "MB", "GB"):
        if abs(n_bytes) < 1000 or unit == "GB":
            return f"{n_bytes:.0f} {unit}" if unit == "B" else f"{n_bytes:.1f} {unit}"
        n_bytes /= 1000
    raise AssertionError  # not reached


def no_space_message(folder: Path, needed_bytes: int | None, *, arg: str = "--out", then: str = "") -> str:
    """The one line for a full disk: the folder, what is free, about what the output needs."""
    try:
        free = size_text(shutil.disk_usage(_nearest_existing(Path(folder))).free)
    except OSError:
        free = "unknown"
    need = f"; it needs about {size_text(needed_bytes)}" if needed_bytes else ""
    return (
        f"{arg} {folder}: no space left on the device ({free} free){need}; accepted: free that much space "
        f"there, or an {arg} on a disk with room{then}"
    )


@contextmanager
def space_for(
    folder: Path, needed_bytes: Callable[[], int | None], *, arg: str = "--out", then: str = ""
) -> Iterator[None]:
    """Turn a full disk (``ENOSPC``, ``EDQUOT``) met in the block into one ConfigError line naming ``folder``
    and ``needed_bytes()`` (about what the output needs; ``then`` is added to the advice)."""
    try:
        yield
    except OSError as e:
        if e.errno not in NO_SPACE:
            raise
        try:
            needed = needed_bytes()
        except Exception:  # noqa: BLE001  (an estimate never hides the line)
            needed = None
        raise ConfigError(no_space_message(folder, needed, arg=arg, then=then)) from None


FICLONE = 0x40049409  # linux/fs.h: _IOW(0x94, 9, int)


def copy_file(src: Path, dst: Path) -> None:
    """``dst`` as a file of its own with ``src``'s bytes and times: a copy-on-write clone where the
    filesystem makes one (Btrfs, XFS: no space used until either file is written), else an in-kernel copy
    (``copy_file_range``), else a plain one. Never a hard link: writing one file never changes the other."""
    Path(dst).parent.mkdir(parents=True, exist_ok=True)
    with open(src, "rb") as fi, open(dst, "wb") as fo:
        try:
            fcntl.ioctl(fo.fileno(), FICLONE, fi.fileno())
        except OSError as e:
            if e.errno in NO_SPACE:
                raise
            _copy_bytes(fi, fo)
    shutil.copystat(src, dst)


def _copy_bytes(fi, fo) -> None:
    size = os.fstat(fi.fileno()).st_size
    done = 0
    try:
        while done < size:
            n = os.copy_file_range(fi.fileno(), fo.fileno(), size - done)
            if n == 0:
                break
            done += n
        return
    except OSError as e:  # not across these filesystems, or not at all: copy through this process
        if e.errno in NO_SPACE:
            raise
    fi.seek(0)
    fo.seek(0)
    fo.truncate()
    shutil.copyfileobj(fi, fo, 1 << 20)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def private_temp_dir(prefix: str) -> Path:
    """A new folder (mode 0700) in the system's temporary folder, named ``<prefix><pid>-<random>``. First
    removes the folders of that prefix whose process has died (killed before it could remove its own), so
    no such folder outlives its command for long. The caller removes its own when done."""
    tmp = Path(tempfile.gettempdir())
    for p in tmp.glob(f"{prefix}*-*"):
        pid = p.name[len(prefix) :].split("-", 1)[0]
        if not pid.isdigit() or _alive(int(pid)) or p.is_symlink() or not p.is_dir():
            continue
        if p.stat().st_uid == os.getuid():  # only this user's: another's is not ours to remove
            shutil.rmtree(p, ignore_errors=True)
    return Path(tempfile.mkdtemp(prefix=f"{prefix}{os.getpid()}-"))


def remove_stale(parent: Path, pattern: str) -> None:
    """Delete what ``pattern`` matches in ``parent``: a killed run's temporary folders or files. Call it only
    holding the output's ``OutputLock``, which proves no live run writes them."""
    for p in Path(parent).glob(pattern):
        if p.is_symlink() or not p.is_dir():
            p.unlink(missing_ok=True)
        else:
            shutil.rmtree(p, ignore_errors=True)


class OutputLock:
    """The one-writer lock on an output path (a folder or a file), held for a ``with`` block.

    The lock is an ``fcntl.flock`` on ``.<name>.lock`` beside the output, with the holder's pid and command
    in it. The kernel releases it when the holder exits or is killed, so a lock file left behind by a dead
    process never blocks anyone. ``held_by`` tells whether another process writes there now.
    """

    def __init__(self, target: str | Path, *, command: str, arg: str = "--out"):
        self.target = Path(target).absolute()
        self.command = command
        self.arg = arg
        self.path = self.target.parent / f".{self.target.name}.lock"
        self._fd: int | None = None

    @classmethod
    def held_by(cls, target: str | Path) -> dict | None:
        """The live holder's record (pid, command) of ``target``'s lock, or None when no one holds it."""
        path = Path(target).absolute().parent / f".{Path(target).name}.lock"
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                return json.loads(os.pread(fd, 4096, 0) or b"{}")
            except ValueError:
                return {}
        finally:
            os.close(fd)
        return None

    def __enter__(self) -> OutputLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                try:
                    holder = json.loads(os.pread(fd, 4096, 0) or b"{}")
                except ValueError:
                    holder = {}
                os.close(fd)
                who = f"`{holder['command']}` (pid {holder['pid']})" if "pid" in holder else "another process"
                raise ConfigError(
                    f"{self.arg} {self.target}: {who} is writing there now; accepted: wait for it to end, or "
                    f"another {self.arg}"
                ) from None
            # the file may have been unlinked by a holder releasing it between our open and our lock
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"pid": os.getpid(), "command": self.command}).encode(), 0)
        self._fd = fd
        return self

    def __exit__(self, *exc: object) -> None:
        if self._fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)
        finally:
            os.close(self._fd)  # closing releases the lock
            self._fd = None
