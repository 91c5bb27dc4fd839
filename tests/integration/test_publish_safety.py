"""`rebar dataset publish --out`: one line for every unusable --out, only its own earlier bundle replaced."""

from __future__ import annotations

from rebar_data.cli import main
from rebar_data.outputs import OutputLock
from tests.read_only import read_only_fixture  # noqa: F401  (the read_only fixture)


def _publish(source, out, *flags) -> int:
    return main(["dataset", "publish", str(source), "--out", str(out), *flags])


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("error: "), err
    return err


def test_an_out_that_is_a_file_or_read_only_is_one_line(source_dataset, tmp_path, capsys, read_only):
    f = tmp_path / "bundle.zip"
    f.write_bytes(b"a user's archive")
    assert _publish(source_dataset, f) == 2
    assert "--out" in (err := _one_line(capsys)) and "is a file" in err, err
    assert f.read_bytes() == b"a user's archive"
    assert _publish(source_dataset, f / "bundle") == 2
    assert "--out" in (err := _one_line(capsys)) and "is a file" in err, err

    ro = read_only(tmp_path / "ro")
    assert _publish(source_dataset, ro / "bundle") == 2
    assert "--out" in (err := _one_line(capsys)) and "not writable" in err, err
    empty = read_only(tmp_path / "empty-ro")
    assert _publish(source_dataset, empty) == 2
    assert "--out" in (err := _one_line(capsys)) and "not writable" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bundle.zip", "empty-ro", "ro"]


def test_force_replaces_only_an_earlier_bundle(source_dataset, tmp_path, capsys):
    user = tmp_path / "release"
    user.mkdir()
    (user / "notes.md").write_text("years of work")
    assert _publish(source_dataset, user, "--force") == 2
    err = _one_line(capsys)
    assert "--out" in err and "did not write" in err, err
    assert [p.name for p in user.iterdir()] == ["notes.md"]

    out = tmp_path / "bundle"
    assert _publish(source_dataset, out) == 0
    (out / "stale.txt").write_text("left by hand")
    capsys.readouterr()
    assert _publish(source_dataset, out) == 2
    assert "--force" in _one_line(capsys)
    assert _publish(source_dataset, out, "--force") == 0
    assert (out / "croissant.json").exists() and not (out / "stale.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bundle", "release"]  # no staging, lock or old copy


def test_a_bundle_being_written_is_not_written_twice(source_dataset, tmp_path, capsys):
    out = tmp_path / "bundle"
    with OutputLock(out, command="rebar dataset publish"):
        assert _publish(source_dataset, out) == 2
        assert "is writing there now" in _one_line(capsys)
    assert not out.exists()


def test_a_read_only_dataset_publishes_into_a_bundle_of_its_own(source_dataset, tmp_path, monkeypatch):
    import hashlib
    import shutil

    from rebar_data.dataset import audit as audit_mod

    report = (source_dataset / "audit" / "report.json").read_text()

    def audit_dataset(ds, *, out=None, **kwargs):  # the real one's report, at once; where it is told to
        out = out or ds / "audit"
        out.mkdir(parents=True)
        (out / "report.json").write_text(report)
        return [], {}

    monkeypatch.setattr(audit_mod, "audit_dataset", audit_dataset)
    src = tmp_path / "ds"
    shutil.copytree(source_dataset, src)
    shutil.rmtree(src / "audit")  # not audited: publish audits it
    for p in [src, *src.rglob("*")]:
        p.chmod(0o555 if p.is_dir() else 0o444)

    def files():
        return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in src.rglob("*") if p.is_file()}

    before = files()
    out = tmp_path / "bundle"
    killed = tmp_path / ".bundle.partial-k1ll3d"  # what a publish killed midway leaves
    killed.mkdir()
    (killed / "README.md").write_text("half")
    try:
        assert _publish(src, out) == 0
        assert files() == before and not (src / "audit").exists()  # nothing written into the input
    finally:
        for p in [src, *src.rglob("*")]:
            p.chmod(0o755 if p.is_dir() else 0o644)
    assert (out / "audit" / "report.json").read_text() == report and not killed.exists()
    img = next((out / "images").rglob("*.png"))
    original = src / img.relative_to(out)
    assert img.stat().st_ino != original.stat().st_ino and original.stat().st_nlink == 1
    img.write_bytes(b"re-saved")  # an edit in the bundle leaves the dataset's image as it was
    assert hashlib.sha256(original.read_bytes()).hexdigest() == before[original]


def test_a_full_disk_during_publish_is_one_line_and_leaves_nothing(
    source_dataset, tmp_path, capsys, monkeypatch
):
    import errno

    from rebar_data.publish import bundle as bundle_mod

    def full(src, staging, *args):
        (staging / "data").mkdir()
        (staging / "data" / "train-00000.parquet").write_bytes(b"PAR1 half")
        raise OSError(errno.ENOSPC, "No space left on device")

    from rebar_data.dataset.layout import DatasetInfo

    info = DatasetInfo.read(source_dataset)  # validated and audited elsewhere: not again here
    monkeypatch.setattr(bundle_mod, "check_source", lambda *args, **kwargs: (info, {"passed": True}))
    monkeypatch.setattr(bundle_mod, "write_shards", full)
    assert _publish(source_dataset, tmp_path / "bundle") == 2
    err = _one_line(capsys)
    assert "no space left" in err and str(tmp_path / "bundle") in err and "needs about" in err, err
    assert list(tmp_path.iterdir()) == []
