"""Tests sit beside what they test: ``tests/<package>/test_<module>[_<topic>].py`` for
``rebar_data/<package>/<module>.py``; tests that drive several packages, or the repository as a whole, are in
``tests/integration/``."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def module_of(test: Path, package_root: Path) -> Path | None:
    """The module ``test`` (a path under tests/) is beside: the longest ``test_<module>`` prefix of its name that
    names a module in the same folder of the package, or None."""
    folder = package_root.joinpath(*test.parent.parts[1:])
    words = test.stem.removeprefix("test_").split("_")
    for n in range(len(words), 0, -1):
        candidate = folder / ("_".join(words[:n]) + ".py")
        if candidate.is_file():
            return candidate
    return None


def strays(tests_root: Path, package_root: Path) -> list[str]:
    found = []
    for test in sorted(tests_root.rglob("test_*.py")):
        rel = test.relative_to(tests_root.parent)
        if rel.parts[1] != "integration" and module_of(rel, package_root) is None:
            found.append(str(rel))
    return found


def test_every_test_file_sits_beside_its_module():
    assert strays(ROOT / "tests", ROOT / "rebar_data") == []


def test_a_stray_test_is_found(tmp_path):
    (tmp_path / "rebar_data" / "servo").mkdir(parents=True)
    (tmp_path / "rebar_data" / "servo" / "ibvs.py").write_text("")
    (tmp_path / "tests" / "servo").mkdir(parents=True)
    (tmp_path / "tests" / "integration").mkdir()
    for name in (
        "servo/test_ibvs.py",
        "servo/test_ibvs_gain.py",
        "servo/test_loop.py",
        "integration/test_x.py",
    ):
        (tmp_path / "tests" / name).write_text("")
    assert strays(tmp_path / "tests", tmp_path / "rebar_data") == ["tests/servo/test_loop.py"]
