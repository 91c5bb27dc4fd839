"""Run a card's code snippet as it runs in a fresh environment holding only the packages it names.

A snippet names what it needs in its first line, ``# pip install NAME ...`` (extras as ``name[extra]``). The
snippet runs in a subprocess of this interpreter without its site-packages (``python -S``), on a path that
holds only the installed files of NAME ... and of what they require (their ``Requires-Dist``, extras
included where asked for, read from the installed metadata), linked into a folder: what ``pip install NAME
...`` would have put in a fresh environment. The standard library is there as always.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

PIP_LINE = re.compile(r"#\s*pip install ([^#\n]+)")


def named_packages(snippet: str) -> list[str]:
    """The requirements of the snippet's ``# pip install ...`` first line (an empty list when it has none)."""
    first = snippet.lstrip().splitlines()[0] if snippet.strip() else ""
    m = PIP_LINE.match(first)
    return m.group(1).split() if m else []


def required_distributions(names: list[str]) -> list[metadata.Distribution]:
    """The installed distributions ``pip install *names`` would bring; skips the test when one of ``names``
    is not installed here."""
    todo = [Requirement(n) for n in names]
    for r in todo:
        try:
            metadata.distribution(r.name)
        except metadata.PackageNotFoundError:
            pytest.skip(f"{r.name} is not installed: the snippet cannot run here")
    seen: set[tuple[str, frozenset]] = set()
    found: dict[str, metadata.Distribution] = {}
    while todo:
        r = todo.pop()
        key = (canonicalize_name(r.name), frozenset(r.extras))
        if key in seen:
            continue
        seen.add(key)
        try:
            dist = metadata.distribution(r.name)
        except metadata.PackageNotFoundError:
            continue  # a requirement this machine lacks; the snippet fails here if it needs it
        found[key[0]] = dist
        for line in dist.requires or []:
            q = Requirement(line)
            if q.marker is None or any(q.marker.evaluate({"extra": e}) for e in ("", *r.extras)):
                todo.append(q)
    return list(found.values())


def fresh_site(names: list[str], folder: Path) -> Path:
    """``folder`` holding links to the installed top-level files and folders (packages, modules, their
    ``.dist-info`` and bundled libraries) of the distributions ``pip install *names`` would bring."""
    folder.mkdir(parents=True, exist_ok=True)
    for dist in required_distributions(names):
        for top in sorted({f.parts[0] for f in dist.files or [] if f.parts and f.parts[0] != ".."}):
            link, target = folder / top, Path(dist.locate_file(top))
            if target.exists() and not link.exists():
                link.symlink_to(target, target_is_directory=target.is_dir())
    return folder


def run_in_fresh_environment(
    snippet: str, cwd: Path, *, names: list[str] | None = None, env: dict | None = None, timeout: float = 600
) -> subprocess.CompletedProcess:
    """Run ``snippet`` from ``cwd`` where only ``names`` (default: its ``# pip install`` line's) are
    installed, the snippet and the packages' folder written beside ``cwd``; ``env`` is the environment
    (default this one), its ``PYTHONPATH`` replaced."""
    names = named_packages(snippet) if names is None else names
    beside = Path(cwd).parent / f"{Path(cwd).name}.fresh"  # the snippet and its packages, outside ``cwd``
    site = fresh_site(names, beside / "packages")
    file = beside / "snippet.py"
    file.write_text(snippet)
    env = {**(os.environ if env is None else env), "PYTHONPATH": str(site), "PYTHONNOUSERSITE": "1"}
    return subprocess.run(
        [sys.executable, "-S", str(file)], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env
    )


def python_blocks(markdown: str) -> list[str]:
    """The ```python blocks of a Markdown text, in order."""
    return re.findall(r"```python\n(.*?)```", markdown, re.S)
