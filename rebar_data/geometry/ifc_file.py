"""An IFC file taken whole or refused: its header's schema, its end, every entity instance parsed.

IfcOpenShell parses a file cut short (an interrupted download) without complaint, and skips a line it cannot
read: either would give a smaller model than the one drawn. So a file is refused, in one ConfigError line,
when its last bytes are not ``END-ISO-10303-21;`` or when the parser holds fewer entity instances than the
file's lines define (the first one lost is named). Both checks read the file once, in the same pass as its
SHA-256, and cost little beside the parse.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

from rebar_data.config import ConfigError

READ_SCHEMAS = ("IFC2X3", "IFC4", "IFC4X3")
PSET_NAME = "RebarServo_Bar"  # the property set `rebar mesh --ifc` writes: BarId, Direction, Layer
END = b"END-ISO-10303-21;"
_TAIL_BYTES = 4096
_BLOCK = 1 << 20
_INSTANCE = re.compile(rb"(?m)^[ \t]*#(\d+)[ \t]*=")


@dataclass(frozen=True)
class IfcFile:
    """A parsed IFC file with what was checked of it."""

    path: Path
    schema: str  # as its header names it
    sha256: str
    model: object  # the ifcopenshell.file


def ifcopenshell_module():
    """IfcOpenShell with the utilities the reader uses, or a ConfigError naming how to install it."""
    try:
        import ifcopenshell
        import ifcopenshell.util.element
        import ifcopenshell.util.placement
        import ifcopenshell.util.unit
    except ImportError:
        raise ConfigError(
            "mesh.kind: ifc needs IfcOpenShell, which is not installed; accepted: install it with "
            '`pip install -e ".[ifc]"` (make setup does)'
        ) from None
    return ifcopenshell


def _where(path: Path) -> str:
    return f"mesh.ifc_path {path}"


def file_schema(path: Path) -> str:
    """The schema an IFC file declares in its header; a ConfigError for anything that is not an IFC file."""
    where = _where(path)
    if not path.exists():
        raise ConfigError(f"{where}: no such file; accepted: an IFC file (.ifc)")
    if path.is_dir():
        raise ConfigError(f"{where}: is a folder; accepted: an IFC file (.ifc)")
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except OSError as e:
        raise ConfigError(
            f"{where}: cannot be read ({e.strerror}); accepted: an IFC file you may read"
        ) from None
    if not head.lstrip(b"\xef\xbb\xbf \t\r\n").startswith(b"ISO-10303-21;"):
        raise ConfigError(
            f"{where}: not an IFC file (no ISO-10303-21 header); accepted: an IFC file in STEP form (.ifc), "
            "not ifcXML or ifcZIP"
        )
    m = re.search(rb"FILE_SCHEMA\s*\(\s*\(\s*'([^']*)'", head)
    if not m:
        raise ConfigError(
            f"{where}: its header names no FILE_SCHEMA; accepted: an IFC2X3, IFC4 or IFC4X3 file"
        )
    name = m.group(1).decode("ascii", "replace").strip().upper()
    for schema in READ_SCHEMAS:
        if name == schema or (schema == "IFC4X3" and name.startswith("IFC4X3_")):
            return name
    raise ConfigError(f"{where}: schema {name} is not read; accepted: IFC2X3, IFC4 or IFC4X3")


def _digest_and_count(path: Path) -> tuple[str, int, bytes]:
    """SHA-256 of the file, an upper bound of its entity instances (lines that start with ``#``) and its
    last bytes, in one read."""
    digest = hashlib.sha256()
    starts, last, tail = 0, b"", b""
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(_BLOCK), b""):
            digest.update(block)
            starts += (last[-1:] + block).count(b"\n#")
            last = block
            tail = (tail + block)[-_TAIL_BYTES:]
    return digest.hexdigest(), starts, tail


def _instances_lost(path: Path, parsed: set[int]) -> tuple[int, int]:
    """How many entity instances the file defines, and the first one the parser does not hold (0: none)."""
    ids = [int(m.group(1)) for m in _INSTANCE.finditer(path.read_bytes())]
    lost = [i for i in ids if i not in parsed]
    return len(ids), (lost[0] if lost else 0)


def open_whole(path: Path) -> IfcFile:
    """Parse ``path`` after its header, its end and its entity count say it is whole (module doc)."""
    schema = file_schema(path)
    ifcopenshell = ifcopenshell_module()
    where = _where(path)
    sha256, starts, tail = _digest_and_count(path)
    if not tail.rstrip(b" \t\r\n\x00\x1a").endswith(END):
        raise ConfigError(
            f"{where}: is not whole: it does not end with END-ISO-10303-21; (a download or copy cut short); "
            "accepted: the complete IFC file"
        )
    try:
        model = ifcopenshell.open(str(path))
    except Exception as e:  # the parser's errors have no common type
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ConfigError(f"{where}: cannot be parsed as IFC ({first}); accepted: a valid IFC file") from None
    ids = model.entity_names()
    if len(ids) < starts:  # a line may start with '#' inside an entity: count exactly before refusing
        total, first_lost = _instances_lost(path, set(ids))
        if first_lost:
            raise ConfigError(
                f"{where}: cannot be parsed as IFC whole: the parser stopped at or skipped #{first_lost} and "
                f"holds {len(ids)} of its {total} entity instances; accepted: a valid IFC file"
            )
    return IfcFile(path, schema, sha256, model)
