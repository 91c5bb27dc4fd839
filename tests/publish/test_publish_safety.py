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
