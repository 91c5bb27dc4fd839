"""``meta/manifest.parquet``: path, size and sha256 of every file of the dataset but itself and audit/."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa

from rebar_data.dataset import layout
from rebar_data.digest import sha256_file
from rebar_data.geometry.export import write_parquet


def listed_files(root: Path) -> list[str]:
    """Every file the manifest must list, as sorted POSIX paths relative to ``root``."""
    out = []
    for p in root.rglob("*"):
        rel = p.relative_to(root).as_posix()
        if p.is_file() and rel != layout.MANIFEST and not rel.startswith(layout.AUDIT_DIR + "/"):
            out.append(rel)
    return sorted(out)


def write_manifest(root: Path) -> pa.Table:
    paths = listed_files(root)
    table = pa.table(
        {
            "path": pa.array(paths, pa.string()),
            "bytes": pa.array([(root / p).stat().st_size for p in paths], pa.int64()),
            "sha256": pa.array([sha256_file(root / p) for p in paths], pa.string()),
        }
    )
    write_parquet(table, root / layout.MANIFEST)
    return table
