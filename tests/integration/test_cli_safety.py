"""Every command's path and number arguments: a bad one is one line naming it, exit status 2, nothing written."""

from __future__ import annotations

import argparse

import pytest

from rebar_data.cli import build_parser, main
from tests.read_only import read_only_fixture  # noqa: F401  (the read_only fixture)

# numeric flags another part of the project owns and bounds itself
ELSEWHERE = {("dataset build", "--workers")}


def _commands(parser: argparse.ArgumentParser, prefix: str = ""):
    """(command name, its parser) for every leaf command."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield prefix.strip(), parser
    for s in subs:
        for name, p in s.choices.items():
            yield from _commands(p, f"{prefix} {name}")


def _numeric_flags():
    for name, p in _commands(build_parser()):
        for a in p._actions:
            flag = a.option_strings[-1] if a.option_strings else a.dest
            if (name, flag) in ELSEWHERE:
                continue
            if a.type in (int, float) or type(a.type).__name__ == "bounded":
                yield name, flag, a


def test_every_numeric_flag_states_and_enforces_its_bounds():
    from rebar_data.arguments import bounded

    flags = list(_numeric_flags())
    assert {(n, f) for n, f, _ in flags} >= {
        ("servo run", "--episodes"),
        ("render", "--frames"),
        ("render", "--seed"),
        ("train", "--epochs"),
        ("detect", "--threshold"),
        ("detect", "--threads"),
        ("score", "--threshold"),
        ("score", "--threads"),
    }
    for name, flag, action in flags:
        if (name, flag) == ("score", "--oks-sigma"):
            continue  # its own one-line check (exit 2 from main), the range in its help
        assert isinstance(action.type, bounded), (name, flag)
        assert str(action.type) in action.help, (name, flag, action.help)
    oks = next(a for n, f, a in flags if (n, f) == ("score", "--oks-sigma"))
    assert "above 0" in oks.help


@pytest.mark.parametrize(
    "args, flag, words",
    [
        (["render", "p.yaml", "--out", "o", "--frames", "0"], "--frames", ">= 1"),
        (["render", "p.yaml", "--out", "o", "--frames", "-3"], "--frames", ">= 1"),
        (["render", "p.yaml", "--out", "o", "--seed", "-1"], "--seed", "from 0 to"),
        (["train", "ds", "--epochs", "0"], "--epochs", ">= 1"),
        (["detect", "x", "--out", "o", "--threshold", "1.5"], "--threshold", "from 0 to 1"),
        (["detect", "x", "--out", "o", "--threshold", "nan"], "--threshold", "from 0 to 1"),
        (["detect", "x", "--out", "o", "--threads", "0"], "--threads", "from 1 to 256"),
        (["score", "x", "--out", "o.parquet", "--threshold", "-1"], "--threshold", "from 0 to 1"),
        (["servo", "run", "s.yaml", "--out", "o", "--episodes", "-1"], "--episodes", ">= 1"),
    ],
)
def test_a_number_out_of_bounds_is_refused_before_any_work(tmp_path, monkeypatch, capsys, args, flag, words):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        main(args)
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and err[-1].startswith("rebar ") and flag in err[-1] and words in err[-1], err
    assert list(tmp_path.iterdir()) == []


@pytest.fixture
def binary(tmp_path):
    p = tmp_path / "photo.yaml"
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 8)
    return p


@pytest.fixture
def dataset(tmp_path):
    """Enough of a dataset folder for the commands to read their settings file next."""
    root = tmp_path / "ds"
    (root / "tables").mkdir(parents=True)
    for t in ("samples", "keypoints"):
        (root / "tables" / f"{t}.parquet").write_bytes(b"")
    return root


def test_a_binary_file_where_yaml_is_wanted_is_one_line(tmp_path, binary, dataset, capsys):
    out = tmp_path / "out"
    for args in (
        ["servo", "run", str(binary), "--out", str(out)],
        ["servo", "check", str(tmp_path), "--thresholds", str(binary)],
        ["train", str(dataset), "--config", str(binary), "--out", str(out)],
        ["mesh", str(binary), "--out", str(out)],
        ["render", str(binary), "--out", str(out)],
        ["dataset", "build", str(binary), "--out", str(out)],
    ):
        assert main(args) == 2, args
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and str(binary) in err and "not a text file" in err, (args, err)
        assert not out.exists()


def _user_folder(path):
    path.mkdir()
    (path / "thesis.tex").write_text("years of work")
    return path


def test_mesh_replaces_only_its_own_earlier_output(tmp_path, root, capsys):
    smoke = str(root / "pipelines/smoke.yaml")
    user = _user_folder(tmp_path / "user")
    assert main(["mesh", smoke, "--out", str(user)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--out" in err and "did not write" in err, err
    assert [p.name for p in user.iterdir()] == ["thesis.tex"]
    out = tmp_path / "mesh"
    assert main(["mesh", smoke, "--out", str(out)]) == 0
    (out / "stale.txt").write_text("from a run before")
    assert main(["mesh", smoke, "--out", str(out), "--rrd", str(tmp_path / "mesh.rrd")]) == 0
    assert (out / "mesh.glb").exists() and not (out / "stale.txt").exists()
    assert main(["mesh", smoke, "--out", str(out), "--rrd", str(tmp_path / "mesh.rrd")]) == 0  # its own
    notes = tmp_path / "notes.rrd"
    notes.write_text("not a recording")
    capsys.readouterr()
    assert main(["mesh", smoke, "--out", str(out), "--rrd", str(notes)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--rrd" in err and "did not write" in err, err
    assert notes.read_text() == "not a recording"


def test_render_refuses_a_folder_it_did_not_write(tmp_path, root, capsys):
    user = _user_folder(tmp_path / "user")
    (user / "frame_000_approach.png").write_bytes(b"a photograph")
    assert main(["render", str(root / "pipelines/smoke.yaml"), "--out", str(user), "--frames", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--out" in err and "did not write" in err, err
    assert (user / "frame_000_approach.png").read_bytes() == b"a photograph"


def test_an_output_swapped_into_a_read_only_folder_is_one_line(tmp_path, root, capsys, read_only):
    parent = tmp_path / "ro"
    (parent / "mesh").mkdir(parents=True)  # empty, so it could be replaced: but not in a read-only folder
    read_only(parent)
    assert main(["mesh", str(root / "pipelines/smoke.yaml"), "--out", str(parent / "mesh")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--out" in err and "not writable" in err, err
    assert list((parent / "mesh").iterdir()) == []
