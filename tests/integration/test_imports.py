"""The package's imports point one way: no cycle anywhere, and each layer imports only the layers below it.

The graph is read from the source with ``ast``, imports inside functions included, so an import put off
until a call still counts.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import rebar_data

ROOT = Path(rebar_data.__file__).parent
PERCEPTION = "rebar_data.perception"
# what each part may not import (a module or any module under it)
FORBIDDEN = {
    f"{PERCEPTION}.inference": [
        f"{PERCEPTION}.networks",
        f"{PERCEPTION}.training",
        f"{PERCEPTION}.evaluation",
        f"{PERCEPTION}.commands",
        "rebar_data.config",
        "rebar_data.pipeline",
        "rebar_data.dataset",
        "rebar_data.geometry",
        "rebar_data.scene",
        "rebar_data.render",
        "rebar_data.labels",
        "rebar_data.servo",
        "rebar_data.publish",
    ],
    f"{PERCEPTION}.networks": [
        f"{PERCEPTION}.training",
        f"{PERCEPTION}.evaluation",
        f"{PERCEPTION}.commands",
    ],
    f"{PERCEPTION}.evaluation": [f"{PERCEPTION}.training", f"{PERCEPTION}.commands"],
    f"{PERCEPTION}.training": [f"{PERCEPTION}.commands"],
    "rebar_data.dataset": [
        "rebar_data.perception",
        "rebar_data.servo",
        "rebar_data.publish",
        "rebar_data.cli",
    ],
    "rebar_data.perception": ["rebar_data.servo", "rebar_data.publish"],
    **{
        f"rebar_data.{lower}": [
            "rebar_data.dataset",
            "rebar_data.perception",
            "rebar_data.servo",
            "rebar_data.publish",
            "rebar_data.bench",
            "rebar_data.cli",
        ]
        for lower in ("geometry", "scene", "render", "labels")
    },
}
# the only packages the run time may import besides the standard library and rebar_data
RUN_TIME_THIRD_PARTY = {
    "numpy",
    "cv2",
    "onnxruntime",
    "openvino",
    "onnx",
}  # onnx: OpenVINO reads the file through it


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """Each module of rebar_data: the rebar_data modules it imports, and the top-level packages of the others."""
    files = {module_name(p): p for p in ROOT.rglob("*.py")}
    inside: dict[str, set[str]] = {}
    outside: dict[str, set[str]] = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        inside[name], outside[name] = set(), set()
        for node in ast.walk(ast.parse(path.read_text())):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(
                        [*package.split(".")[: len(package.split(".")) - node.level + 1], base]
                    ).strip(".")
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base for a in node.names]
            for t in targets:
                if t.split(".")[0] != "rebar_data":
                    outside[name].add(t.split(".")[0])
                    continue
                while t not in files and "." in t:
                    t = t.rpartition(".")[0]
                if t != name:
                    inside[name].add(t)
    return inside, outside


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def under(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def test_no_import_cycle():
    inside, _ = import_graph()
    assert cycles(inside) == []


def test_each_layer_imports_only_the_layers_below():
    inside, _ = import_graph()
    wrong = sorted(
        f"{module} imports {target}"
        for module, targets in inside.items()
        for part, forbidden in FORBIDDEN.items()
        if under(module, part)
        for target in targets
        for f in forbidden
        if under(target, f)
    )
    assert wrong == []


def test_the_run_time_imports_no_other_third_party_package():
    _, outside = import_graph()
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    wrong = sorted(
        f"{module} imports {top}"
        for module, tops in outside.items()
        if under(module, f"{PERCEPTION}.inference")
        for top in tops - stdlib - RUN_TIME_THIRD_PARTY
    )
    assert wrong == []


def test_a_cycle_is_found():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


RUN_TIME_CHECK = """
import sys
import numpy as np
from rebar_data.perception import Detector

detector = Detector.load(threads=1)
rgb = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
depth = np.full((480, 640), 0.6, np.float32)
detector.detect(rgb)
detector.detect(rgb, depth=depth)
detector.detect(rgb, point="crossing")
loaded = sorted(sys.modules)
print("\\n".join(loaded))
"""


def test_the_run_time_loads_no_training_code():
    """Loading the shipped model and detecting, in a fresh interpreter, imports no torch, SciPy, training,
    network, evaluation, dataset or geometry module."""
    from rebar_data.perception.inference.detector import SHIPPED_MODEL

    if not SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    out = subprocess.run(
        [sys.executable, "-c", RUN_TIME_CHECK], capture_output=True, text=True, check=True, cwd=ROOT.parent
    ).stdout.split()
    assert "rebar_data.perception.inference.detector" in out
    forbidden = (
        "torch",
        "scipy",
        f"{PERCEPTION}.training",
        f"{PERCEPTION}.networks",
        f"{PERCEPTION}.evaluation",
        "rebar_data.dataset",
        "rebar_data.geometry",
    )
    assert [m for m in out if any(under(m, f) for f in forbidden)] == []
