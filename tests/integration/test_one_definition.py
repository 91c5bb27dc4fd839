"""One definition each: no two classes of the package hold a camera's intrinsics, and no public name is defined
at the top of two modules (an import that passes a name on is not a definition).

A config schema (a ``Strict`` model: what a pipeline file may say, such as explicit intrinsics) describes a file's
keys, not a camera; it is turned into the camera in one place (``scene/cameras.py``) and is not counted.

Names every module of a kind defines because its package looks them up by name are the exception, listed in
``PROTOCOLS`` with the place that looks them up.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2] / "rebar_data"
INTRINSICS = {"fx", "fy", "cx", "cy"}
# name -> the modules that define it, as the code that looks them up by name requires
PROTOCOLS = {
    "register": "each `commands` module and `bench.py`: rebar_data/cli.py imports them by name",
    "run": "each package's `bench` module: rebar_data/bench.py calls `run` of each",
    "main": "modules run with `python -m`",
    "COMMAND": "each command module's own name for its outputs' marks, passed to rebar_data/outputs.py",
    **dict.fromkeys(
        ("FILE", "build", "save", "load"),
        "each later stage's training module (refine, depth_check, crossing_point): training/export.py and "
        "later_stages.py call them on the module",
    ),
}


def definitions(tree: ast.Module) -> list[str]:
    """The public names a module defines at its top level."""
    names: list[str] = []
    for node in tree.body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.append(node.name)
        elif isinstance(node, ast.Assign):
            for target in node.targets:  # `a = ...` and `a, b = ...`
                names += [t.id for t in ast.walk(target) if isinstance(t, ast.Name)]
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.append(node.target.id)
    return [n for n in names if not n.startswith("_")]


def fields(cls: ast.ClassDef) -> set[str]:
    """The fields a class body declares (annotations, and a NamedTuple's or dataclass's assignments)."""
    out = {n.target.id for n in cls.body if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name)}
    for init in (n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "__init__"):
        out |= {a.arg for a in init.args.args + init.args.kwonlyargs}
    return out


def modules(root: Path = ROOT) -> dict[str, ast.Module]:
    return {str(p.relative_to(root.parent)): ast.parse(p.read_text()) for p in sorted(root.rglob("*.py"))}


def defined_twice(trees: dict[str, ast.Module]) -> dict[str, list[str]]:
    where: dict[str, list[str]] = defaultdict(list)
    for path, tree in trees.items():
        for name in definitions(tree):
            where[name].append(path)
    return {n: paths for n, paths in where.items() if len(paths) > 1 and n not in PROTOCOLS}


def intrinsics_classes(trees: dict[str, ast.Module]) -> list[str]:
    return [
        f"{path}::{node.name}"
        for path, tree in trees.items()
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef) and fields(node) >= INTRINSICS and not is_schema(node)
    ]


def is_schema(cls: ast.ClassDef) -> bool:
    return any(isinstance(b, ast.Name) and b.id == "Strict" for b in cls.bases)


def test_one_class_holds_a_cameras_intrinsics():
    found = intrinsics_classes(modules())
    assert len(found) == 1, found


def test_no_public_name_is_defined_in_two_modules():
    assert defined_twice(modules()) == {}


def test_the_checks_find_what_they_look_for(tmp_path):
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "a.py").write_text(
        "class Camera:\n    fx: float\n    fy: float\n    cx: float\n    cy: float\n"
    )
    (package / "b.py").write_text(
        "from typing import NamedTuple\nclass Cam(NamedTuple):\n    fx: float\n    fy: float\n    cx: float\n"
        "    cy: float\nLIMIT = 3\ndef register(sub): ...\n"
    )
    (package / "c.py").write_text(
        "from pkg.b import LIMIT\nLIMIT_2 = 4\ndef register(sub): ...\n_private = 1\nsave, keep = 1, 2\n"
    )
    (package / "e.py").write_text("keep = 3\n")
    (package / "d.py").write_text(
        "LIMIT = 5\nclass Pinhole:\n    def __init__(self, fx, fy, cx, cy): ...\n"
        "class Keys(Strict):\n    fx: float\n    fy: float\n    cx: float\n    cy: float\n"
    )
    trees = modules(package)
    assert defined_twice(trees) == {"LIMIT": ["pkg/b.py", "pkg/d.py"], "keep": ["pkg/c.py", "pkg/e.py"]}
    assert intrinsics_classes(trees) == ["pkg/a.py::Camera", "pkg/b.py::Cam", "pkg/d.py::Pinhole"]
