"""A damaged or read-only dataset as every command that reads it meets it: one line naming the file and
what was expected, nothing written into it, and (for a full disk) nothing half-written left."""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
from pathlib import Path

import pytest

from rebar_data.cli import main
from rebar_data.dataset import layout
from tests.dataset.conftest import write_config


def _one_line(capsys) -> str:
    """The one line on stderr (progress bars aside), an ``error:`` line."""
    lines = [x for x in capsys.readouterr().err.splitlines() if x.strip() and "%|" not in x]
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


def _files(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture
def truncated(tmp_path) -> Path:
    """A dataset folder whose meta/info.json was cut short (a copy stopped midway)."""
    ds = tmp_path / "ds"
    (ds / "meta").mkdir(parents=True)
    (ds / "tables").mkdir()
    (ds / layout.INFO).write_text('{"name": "tiny", "version": "0.0.1", "schema_vers')
    return ds


@pytest.mark.parametrize(
    "argv",
    [
        ["dataset", "audit", "{ds}"],
        ["dataset", "diff", "{ds}", "{ds}"],
        ["dataset", "publish", "{ds}", "--out", "{out}"],
    ],
    ids=["audit", "diff", "publish"],
)
def test_a_truncated_info_json_is_one_line_naming_it(truncated, tmp_path, capsys, argv):
    before = _files(truncated)
    args = [a.format(ds=truncated, out=tmp_path / "bundle") for a in argv]
    assert main(args) == 2
    err = _one_line(capsys)
    assert str(truncated / layout.INFO) in err and "not valid JSON" in err and "expected" in err, err
    assert _files(truncated) == before and not (tmp_path / "bundle").exists()


def test_a_truncated_table_is_one_line_naming_it(tiny_dataset, tmp_path, capsys):
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    table = ds / layout.KEYPOINTS
    table.write_bytes(table.read_bytes()[:100])
    assert main(["dataset", "diff", str(tiny_dataset), str(ds)]) == 2
    err = _one_line(capsys)
    assert str(table) in err and "Parquet table" in err, err


def test_a_read_only_dataset_is_told_where_its_audit_would_write(tiny_dataset, tmp_path, capsys):
    """Refused before any work, naming --out; with --out the report goes there (publish's test runs one)."""
    from rebar_data.dataset.commands import audit_out

    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    shutil.rmtree(ds / layout.AUDIT_DIR, ignore_errors=True)
    for p in [ds, *ds.rglob("*")]:
        p.chmod(0o555 if p.is_dir() else 0o444)
    real = os.access  # as root the mode does not stop a write: the command asks os.access, as a user's would

    def fake(path, mode, *args, **kwargs):
        if mode & os.W_OK and Path(path).absolute().is_relative_to(ds):
            return False
        return real(path, mode, *args, **kwargs)

    before = _files(ds)
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(os, "access", fake)
            assert main(["dataset", "audit", str(ds)]) == 2
            err = _one_line(capsys)
            assert "read-only" in err and str(ds / layout.AUDIT_DIR) in err and "--out" in err, err
            assert audit_out(ds, str(tmp_path / "report")) == tmp_path / "report"
        assert _files(ds) == before and not (ds / layout.AUDIT_DIR).exists()
    finally:
        for p in [ds, *ds.rglob("*")]:
            p.chmod(0o755 if p.is_dir() else 0o644)


def test_a_full_disk_during_a_build_is_one_line_and_leaves_no_temporary_file(tmp_path, capsys, monkeypatch):
    real = Path.write_bytes

    def half_then_full(self, data):
        if self.name.endswith(".tmp"):  # a frame's file, written via a temporary name
            real(self, data[: len(data) // 2])
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, data)

    monkeypatch.setattr(Path, "write_bytes", half_then_full)
    config = write_config(tmp_path / "cfg")
    assert main(["dataset", "build", str(config), "--out", str(tmp_path / "data"), "--workers", "1"]) == 2
    err = _one_line(capsys)
    assert "no space left" in err and str(tmp_path / "data" / "tiny") in err and "needs about" in err, err
    assert "--resume" in err, err
    assert not [p for p in (tmp_path / "data").rglob("*") if ".tmp" in p.name]
