"""Every repository path the README, ARCHITECTURE.md, docs/ and the package's docstrings name exists.

A path is named when it starts with one of the repository's folders (``rebar_data/``, ``pipelines/``, ``eval/``,
``schemas/``, ``docs/``, ``tests/``, ``.ci/``), when it is a module path inside the package (``servo/episode.py``),
or when a Markdown link points at a relative file. A path with a placeholder in it (``<split>``, ``*``, ``{...}``,
``NAME``) stands for many and is not checked; neither are outputs (``runs/``, ``data/``) nor paths inside a
dataset or a bundle.
"""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = ("rebar_data", "pipelines", "eval", "schemas", "docs", "tests", ".ci")
PACKAGES = ("geometry", "scene", "render", "labels", "dataset", "publish", "perception", "servo")
_STARTS = "|".join(re.escape(f) for f in FOLDERS + PACKAGES)
TOKEN = re.compile(rf"(?<![\w./-])((?:{_STARTS})/[\w./-]*[\w/])")
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
WORD = re.compile(r"[^\s`'\"()\[\],;]+")
# a Markdown file named without a folder (``DESIGN.md``); outputs of a run (``report.md``, a servo map's
# ``map.md``) are not files here
BARE_MD = re.compile(r"(?<![\w./(-])((?!(?:report|map)\.md)[\w-]+\.md)(?![\w.])")
PLACEHOLDER = re.compile(r"[<>*{}]|NAME|\.\.\.|/X\b|\bmy-")


@functools.cache
def markdown_files() -> set[str]:
    """The names of the repository's Markdown files (outputs and environments left out)."""
    skip = {".venv", ".git", "data", "runs", "node_modules"}
    return {p.name for p in ROOT.rglob("*.md") if not skip & set(p.relative_to(ROOT).parts)}


def documents() -> list[Path]:
    docs = [ROOT / "README.md", ROOT / "ARCHITECTURE.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return docs + sorted((ROOT / "rebar_data").rglob("README.md"))


def docstrings(path: Path) -> str:
    tree = ast.parse(path.read_text())
    nodes = [
        tree,
        *(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)),
    ]
    return "\n".join(d for n in nodes if (d := ast.get_docstring(n)))


def named_paths(text: str) -> set[str]:
    """The repository paths ``text`` names (placeholders left out)."""
    found = set()
    for m in TOKEN.finditer(text):
        path = m.group(1).rstrip(".")
        first = path.split("/")[0]
        if first in PACKAGES and not path.endswith(".py"):
            continue  # a short form names a module; other words/like/this are prose
        word = WORD.match(text, m.start()).group(0)  # the whole word: `pipelines/wide-*.yaml`
        if not PLACEHOLDER.search(word):
            found.add(path)
    for m in BARE_MD.finditer(text):
        found.add(m.group(1))
    return found


def exists(path: str, base: Path) -> bool:
    candidates = [ROOT / path, base / path, ROOT / f"{path}.yaml"]  # a pipeline or suite named by its stem
    if "/" not in path:  # a bare Markdown file: anywhere in the repository
        return path in markdown_files()
    if path.split("/")[0] in PACKAGES:
        candidates.append(ROOT / "rebar_data" / path)
    return any(c.exists() for c in candidates)


def missing_in(text: str, base: Path) -> list[str]:
    gone = sorted(p for p in named_paths(text) if not exists(p, base))
    for m in LINK.finditer(text):
        target = m.group(1)
        if re.match(r"[a-z]+:", target) or PLACEHOLDER.search(target):
            continue
        if not (base / target).exists():
            gone.append(f"link {target}")
    return gone


@pytest.mark.parametrize("doc", documents(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_path_a_document_names_exists(doc):
    assert doc.exists(), f"{doc.relative_to(ROOT)} is missing"
    assert missing_in(doc.read_text(), doc.parent) == []


def test_every_path_a_docstring_names_exists():
    gone = {}
    for module in sorted((ROOT / "rebar_data").rglob("*.py")):
        if missing := missing_in(docstrings(module), module.parent):
            gone[str(module.relative_to(ROOT))] = missing
    assert gone == {}


def test_a_missing_path_is_found(tmp_path):
    text = (
        "see `rebar_data/servo/no_such_module.py`, `servo/episode.py`, [the guide](no-such.md), "
        "`pipelines/<name>.yaml`, `pipelines/wide-*.yaml`, `pipelines/wide-tunnel-a`, `runs/eval/ci`, "
        "the contract in DESIGN.md and a run's report.md"
    )
    assert missing_in(text, tmp_path) == [
        "DESIGN.md",
        "rebar_data/servo/no_such_module.py",
        "link no-such.md",
    ]
