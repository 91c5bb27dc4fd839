"""``rebar dataset publish``: a release bundle that others can load, cite and check without this toolkit.

The bundle holds the ready-to-train Parquet shards (Hugging Face layout, images embedded), the dataset
card (``README.md``), Croissant metadata (``croissant.json``), the YOLO and COCO views, the full source
tables, the build's ``meta/info.json`` (and ``meta/mesh.ifc``, for bars read from IFC), the audit report and
``SHA256SUMS``. Only a dataset that validates and passes its audit is published. Like a build, the bundle is written to a staging folder
and swapped into place, so an interrupted publish never leaves a folder that looks finished; an existing
``--out`` is replaced only when it holds an earlier bundle (and ``--force`` says so), one publish at a time.
The bundle's files are its own (copies, or copy-on-write clones where the filesystem makes them): editing
one never changes the dataset. Nothing is written into the dataset, so a read-only one publishes: a
dataset without an audit report is audited into the bundle's ``audit/``.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import shutil
import sys
import tempfile
from collections.abc import Collection
from pathlib import Path

import pyarrow.parquet as pq
import yaml

from rebar_data.config import ConfigError
from rebar_data.dataset import layout
from rebar_data.dataset.layout import DatasetFormatError, DatasetInfo
from rebar_data.dataset.writers.card import CARD
from rebar_data.digest import sha256_file
from rebar_data.outputs import OutputLock, copy_file, output_folder, remove_stale, replace_folder, space_for
from rebar_data.publish.card import LICENSES, bundle_card, citation, license_url
from rebar_data.publish.croissant import croissant_metadata
from rebar_data.publish.rows import write_shards

COMMAND = "rebar dataset publish"
CROISSANT = "croissant.json"
CHECKSUMS = "SHA256SUMS"
VIEW_DIRS = ("images", "labels", "annotations", "tables")
MAP_DIRS = ("depth", "sensor_depth", "instances")
AUDIT_FILES = (
    "report.json",
    "report.md",
    "contact_sheet.png",
    "keypoints_per_image.png",
    "visibility.png",
    "coverage.png",
)


def publication_date() -> str:
    """Today (UTC), or the date of ``SOURCE_DATE_EPOCH`` when set, so a release can be made reproducibly."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    when = dt.datetime.fromtimestamp(int(epoch), dt.UTC) if epoch else dt.datetime.now(dt.UTC)
    return when.date().isoformat()


def _copy_tree(src: Path, dst: Path, *, skip: Collection[Path] = ()) -> None:
    for p in sorted(src.rglob("*")):
        if p.is_file() and p not in skip:
            copy_file(p, dst / p.relative_to(src))


def check_source(dataset: Path) -> tuple[DatasetInfo, dict | None]:
    """The dataset's info and its audit report (None when it has none); refuses a dataset that does not
    validate."""
    from rebar_data.dataset.validate import validate_dataset

    try:
        info = DatasetInfo.read(dataset)
    except DatasetFormatError as e:
        raise ConfigError(str(e)) from None
    # files other tools add (validate's FOREIGN_FILES) are notes there, and left out of the bundle
    failures = validate_dataset(dataset, note=lambda line: print(line, file=sys.stderr))
    if failures:
        raise ConfigError(
            f"{dataset} does not validate ({len(failures)} failures, first: {failures[0]}); accepted: a "
            "dataset that passes `rebar dataset validate`"
        )
    report = dataset / layout.AUDIT_DIR / "report.json"
    if not report.exists():
        return info, None
    try:
        audit = json.loads(report.read_bytes())
    except ValueError as e:
        raise ConfigError(
            f"{report}: not valid JSON ({e}); accepted: the report `rebar dataset audit` writes (run it again)"
        ) from None
    return info, audit if isinstance(audit, dict) else {}


def check_audit(dataset: Path, audit: dict, *, allow_failed_audit: bool) -> None:
    """Refuse a dataset whose audit failed, unless ``allow_failed_audit``."""
    if not audit.get("passed") and not allow_failed_audit:
        failed = [c["name"] for c in audit.get("checks", []) if not c["passed"]]
        raise ConfigError(
            f"{dataset} fails its audit ({', '.join(failed)}); accepted: a dataset that passes "
            "`rebar dataset audit`, or --allow-failed-audit to publish it with the failures in its card"
        )


def bundle_bytes(src: Path, *, maps: bool) -> int:
    """About how much a bundle of ``src`` takes: its copied files, and the images again in the shards."""
    dirs = VIEW_DIRS + (MAP_DIRS if maps else ()) + (layout.AUDIT_DIR, "meta")
    copied = sum(p.stat().st_size for d in dirs for p in (src / d).rglob("*") if p.is_file())
    return copied + sum(p.stat().st_size for p in (src / "images").rglob("*") if p.is_file())


def _write_data_yaml(src: Path, bundle: Path) -> None:
    """Ultralytics' dataset file without ``path``: Ultralytics then takes the folder of data.yaml."""
    data = yaml.safe_load((src / layout.DATA_YAML).read_text())
    data.pop("path", None)
    text = (
        "# Ultralytics YOLO pose dataset. No `path`: Ultralytics resolves train/val/test against the folder of\n"
        "# this file when it is given by absolute path.\n" + yaml.safe_dump(data, sort_keys=False)
    )
    (bundle / layout.DATA_YAML).write_text(text)


def _single_files(bundle: Path) -> dict[str, dict]:
    """The single files Croissant lists, with their hashes, sizes, formats and descriptions."""
    listed = {
        "tables/samples.parquet": (
            "application/x-parquet",
            "one row per image: camera, scene and randomization",
        ),
        "tables/keypoints.parquet": ("application/x-parquet", "one row per crossing per image"),
        "meta/info.json": (
            "application/json",
            "the generator's record of the build: provenance, counts, conventions",
        ),
        layout.DATA_YAML: ("application/x-yaml", "Ultralytics YOLO pose dataset file"),
        CARD: ("text/markdown", "the dataset card"),
    }
    if (bundle / layout.MESH_IFC).is_file():
        listed[layout.MESH_IFC] = ("application/x-step", "the IFC building model the bars were read from")
    for p in sorted((bundle / "annotations").glob("*.json")):
        listed[f"annotations/{p.name}"] = ("application/json", f"COCO keypoints of the {p.stem} split")
    return {
        rel: {
            "sha256": sha256_file(bundle / rel),
            "bytes": (bundle / rel).stat().st_size,
            "encodingFormat": fmt,
            "description": what,
        }
        for rel, (fmt, what) in listed.items()
    }


def _table_meanings() -> dict[str, dict[str, str]]:
    from rebar_data.dataset.validate import field_list

    return {t: {f["name"]: f["meaning"] for f in field_list(t)} for t in ("samples", "keypoints")}


def write_checksums(bundle: Path) -> int:
    """``SHA256SUMS`` in ``sha256sum`` format over every other file; returns how many it lists."""
    files = sorted(p for p in bundle.rglob("*") if p.is_file() and p.name != CHECKSUMS)
    lines = [f"{sha256_file(p)}  {p.relative_to(bundle).as_posix()}\n" for p in files]
    (bundle / CHECKSUMS).write_text("".join(lines))
    return len(lines)


def is_bundle(folder: Path) -> bool:
    """``folder`` holds a bundle `rebar dataset publish` wrote: its card, Croissant file and checksums, the
    checksums listing the Croissant file."""
    sums = folder / CHECKSUMS
    try:
        listed = f"  {CROISSANT}\n" in sums.read_text()
    except (OSError, UnicodeDecodeError):
        return False
    return listed and (folder / CROISSANT).is_file() and (folder / CARD).is_file()


def check_bundle_out(out: Path, *, force: bool) -> Path:
    """``out`` as a bundle may be written there: new, empty, or (with ``force``) an earlier bundle."""
    output_folder(out, arg="--out", command=COMMAND, owned=is_bundle, swapped=True)
    if out.exists() and any(out.iterdir()) and not force:
        raise ConfigError(
            f"--out {out}: holds an earlier bundle; accepted: --force to replace it, or a new folder"
        )
    return out


def publish_dataset(
    dataset: str | Path,
    out: str | Path,
    *,
    license_id: str = "cc-by-4.0",
    maps: bool = False,
    force: bool = False,
    allow_failed_audit: bool = False,
) -> Path:
    """Write the release bundle of ``dataset`` to ``out`` and return ``out``.

    Args:
        license_id: a Hugging Face license id (see ``card.LICENSES``).
        maps: also ship the depth maps (exact and sensor) and instance maps (as PNG files).
        force: replace ``out`` when it holds an earlier bundle (a folder holding anything else is refused).
        allow_failed_audit: publish a dataset whose audit failed (the card says so).
    """
    src = Path(dataset).resolve()
    out = Path(out).resolve()
    if license_id not in LICENSES:
        raise ConfigError(f"--license {license_id}: unknown; accepted: {', '.join(LICENSES)}")
    if out == src or src in out.parents or out in src.parents:
        raise ConfigError(f"--out {out}: inside or around the dataset; accepted: a folder outside {src}")
    check_bundle_out(out, force=force)
    info, audit = check_source(src)
    if audit is not None:
        check_audit(src, audit, allow_failed_audit=allow_failed_audit)
    with (
        space_for(out, lambda: bundle_bytes(src, maps=maps)),
        OutputLock(out, command=COMMAND),
    ):
        check_bundle_out(
            out, force=force
        )  # again under the lock: another publish may have finished meanwhile
        remove_stale(out.parent, f".{out.name}.partial-*")  # a killed publish's (the lock proves it dead)
        staging = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.partial-"))
        try:
            if audit is None:  # audited into the bundle: nothing is written into the dataset
                audit = _audit_into(src, staging / layout.AUDIT_DIR)
                check_audit(src, audit, allow_failed_audit=allow_failed_audit)
                audit_src = staging / layout.AUDIT_DIR
            else:
                audit_src = src / layout.AUDIT_DIR
            _write_bundle(src, staging, info, audit, audit_src, license_id=license_id, maps=maps)
            replace_folder(staging, out)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    return out


def _audit_into(src: Path, folder: Path) -> dict:
    """Audit ``src`` with its report, plots and contact sheet written to ``folder``; the report."""
    from rebar_data.dataset.audit import audit_dataset

    audit_dataset(src, out=folder)
    return json.loads((folder / "report.json").read_text())


def _write_bundle(
    src: Path, staging: Path, info: DatasetInfo, audit: dict, audit_src: Path, *, license_id: str, maps: bool
) -> None:
    """Every file of the bundle of ``src`` into the folder ``staging`` (empty but for its ``audit/`` when
    ``audit_src`` is there)."""
    from rebar_data.dataset.validate import foreign_files

    samples = pq.read_table(src / layout.SAMPLES)
    keypoints = pq.read_table(src / layout.KEYPOINTS)
    shards = write_shards(src, staging, samples, keypoints)
    foreign = {src / rel for rel in foreign_files(src)}  # never published
    for d in VIEW_DIRS + (MAP_DIRS if maps else ()):
        if (src / d).is_dir():
            _copy_tree(src / d, staging / d, skip=foreign)
    copy_file(src / layout.INFO, staging / layout.INFO)
    if (src / layout.MESH_IFC).is_file():
        copy_file(src / layout.MESH_IFC, staging / layout.MESH_IFC)
    _write_data_yaml(src, staging)
    if audit_src != staging / layout.AUDIT_DIR:
        for name in AUDIT_FILES:
            if (audit_src / name).exists():
                copy_file(audit_src / name, staging / layout.AUDIT_DIR / name)

    date = publication_date()
    splits = list(dict.fromkeys(s.split for s in shards))
    (staging / CARD).write_text(
        bundle_card(info, audit=audit, license_id=license_id, date_published=date, splits=splits, maps=maps)
    )
    n_images = samples.num_rows
    croissant = croissant_metadata(
        staging,
        info,
        description=(
            f"{n_images} synthetic images of rebar with exact keypoints at the bar intersections "
            f"(visibility, box and 3D point), generated by {info.generator.get('name')} "
            f"{info.generator.get('version')} from a recorded config and seed. {info.description}".strip()
        ),
        license_url=license_url(license_id),
        cite_as=citation(info, date[:4]),
        date_published=date,
        files=_single_files(staging),
        meanings=_table_meanings(),
    )
    (staging / CROISSANT).write_text(json.dumps(croissant, indent=2) + "\n")
    write_checksums(staging)
