"""``rebar dataset validate``: every file against the contract in ``schemas/`` and the manifest.

Each failure is one line, ``<check>: <what is wrong>``; the dataset is valid when there are none.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import jsonschema
import pyarrow as pa
import pyarrow.parquet as pq
import yaml

from rebar_data.dataset import layout
from rebar_data.dataset.layout import DatasetFormatError, DatasetInfo
from rebar_data.dataset.writers.manifest import listed_files, sha256_file

SCHEMAS = Path(__file__).resolve().parents[2] / "schemas"
MAX_PER_CHECK = 5  # failures reported per check before summarising the rest

_TYPES = {
    "string": pa.string(),
    "int8": pa.int8(),
    "int16": pa.int16(),
    "int32": pa.int32(),
    "int64": pa.int64(),
    "float64": pa.float64(),
    "bool": pa.bool_(),
    "list<float64>[16]": pa.list_(pa.float64(), 16),
}


def field_list(table: str) -> list[dict]:
    return yaml.safe_load((SCHEMAS / "tables" / f"{table}.yaml").read_text())["fields"]


def json_schema(name: str) -> dict:
    return json.loads((SCHEMAS / f"{name}.schema.json").read_text())


class Failures:
    def __init__(self) -> None:
        self.lines: list[str] = []
        self._per_check: dict[str, int] = {}

    def add(self, check: str, detail: str) -> None:
        n = self._per_check.get(check, 0) + 1
        self._per_check[check] = n
        if n <= MAX_PER_CHECK:
            self.lines.append(f"{check}: {detail}")
        elif n == MAX_PER_CHECK + 1:
            self.lines.append(f"{check}: (further failures of this check not shown)")

    def __bool__(self) -> bool:
        return bool(self.lines)


def validate_dataset(path: Path) -> list[str]:
    """All contract violations of the dataset at ``path`` (empty when it is valid)."""
    path = Path(path)
    f = Failures()
    if not (path / layout.INFO).exists():
        f.add("layout", f"{layout.INFO} is missing; is {path} a dataset folder (<root>/<name>/v<version>)?")
        return f.lines
    info_dict = _check_info(path, f)
    _check_manifest(path, f)
    _check_data_yaml(path, info_dict, f)
    samples = _check_table(path, layout.SAMPLES, "samples", f)
    keypoints = _check_table(path, layout.KEYPOINTS, "keypoints", f)
    if samples is not None and keypoints is not None:
        _check_rows(path, samples, keypoints, info_dict, f)
        _check_yolo(path, samples, f)
    _check_coco(path, samples, f)
    return f.lines


def _check_info(path: Path, f: Failures) -> dict:
    try:
        d = json.loads((path / layout.INFO).read_text())
    except json.JSONDecodeError as e:
        f.add("info", f"{layout.INFO} is not valid JSON: {e}")
        return {}
    for err in sorted(jsonschema.Draft202012Validator(json_schema("info")).iter_errors(d), key=str):
        where = "/".join(str(p) for p in err.absolute_path) or "(top level)"
        f.add("info", f"{layout.INFO} {where}: {err.message}")
    try:
        DatasetInfo.from_dict(d)
    except (DatasetFormatError, TypeError) as e:
        f.add("info", str(e))
    return d


def _check_manifest(path: Path, f: Failures) -> None:
    if not (path / layout.MANIFEST).exists():
        f.add("manifest", f"{layout.MANIFEST} is missing")
        return
    man = pq.read_table(path / layout.MANIFEST).to_pydict()
    listed = dict(zip(man["path"], zip(man["bytes"], man["sha256"], strict=True), strict=True))
    for rel, (size, digest) in listed.items():
        p = path / rel
        if not p.exists():
            f.add("manifest", f"{rel} is listed but missing")
        elif p.stat().st_size != size or sha256_file(p) != digest:
            f.add("manifest", f"{rel} does not match its sha256 in the manifest (changed since the build)")
    for rel in sorted(set(listed_files(path)) - set(listed)):
        f.add("manifest", f"{rel} is not in the manifest")


def _check_data_yaml(path: Path, info: dict, f: Failures) -> None:
    p = path / layout.DATA_YAML
    if not p.exists():
        f.add("data.yaml", "missing")
        return
    try:
        d = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        f.add("data.yaml", f"is not valid YAML: {' '.join(str(e).split())}")
        return
    names = d.get("names") if isinstance(d, dict) else None
    if isinstance(names, dict):  # YAML reads the class ids as integers; JSON Schema keys are strings
        d = {**d, "names": {str(k): v for k, v in names.items()}}
    for err in sorted(jsonschema.Draft202012Validator(json_schema("data_yaml")).iter_errors(d), key=str):
        where = "/".join(str(x) for x in err.absolute_path) or "(top level)"
        f.add("data.yaml", f"{where}: {err.message}")
    sigma = info.get("oks_sigma")
    if isinstance(d, dict) and "kpt_oks_sigmas" in d and d["kpt_oks_sigmas"] != [sigma]:
        f.add("data.yaml", f"kpt_oks_sigmas = {d['kpt_oks_sigmas']!r}; expected [{sigma}] (info.json)")


def _check_table(path: Path, rel: str, name: str, f: Failures) -> pa.Table | None:
    p = path / rel
    if not p.exists():
        f.add(name, f"{rel} is missing")
        return None
    try:
        t = pq.read_table(p)
    except (pa.ArrowInvalid, OSError) as e:
        f.add(name, f"{rel} is not a readable Parquet file: {e}")
        return None
    for fld in field_list(name):
        if fld["name"] not in t.column_names:
            f.add(name, f"column {fld['name']} is missing")
            continue
        want, got = _TYPES[fld["type"]], t.schema.field(fld["name"]).type
        if got != want:
            f.add(name, f"column {fld['name']} has type {got}; the schema says {fld['type']}")
    return t


def _check_rows(path: Path, samples: pa.Table, keypoints: pa.Table, info: dict, f: Failures) -> None:
    s = samples.to_pandas()
    k = keypoints.to_pandas()
    if s["image_id"].duplicated().any():
        f.add("samples", f"duplicate image_id {s['image_id'][s['image_id'].duplicated()].iloc[0]}")
    bad_split = set(s["split"]) - set(layout.SPLITS)
    if bad_split:
        f.add("samples", f"unknown split {sorted(bad_split)[0]!r}; accepted: {', '.join(layout.SPLITS)}")
    for row in s.itertuples():
        if not (path / row.file_name).exists():
            f.add("images", f"{row.file_name} is missing")
    known = set(s["image_id"])
    orphans = set(k["image_id"]) - known
    if orphans:
        f.add("keypoints", f"rows for unknown image {sorted(orphans)[0]}")
    if not set(k["visibility"].unique()) <= {0, 1, 2}:
        f.add("keypoints", f"visibility values {sorted(set(k['visibility'].unique()))}; accepted: 0, 1, 2")
    size = s.set_index("image_id")[["width", "height"]]
    k = k.join(size, on="image_id")
    shown = k[k["visibility"] > 0]
    outside = shown[(shown.u < 0) | (shown.u >= shown.width) | (shown.v < 0) | (shown.v >= shown.height)]
    for row in outside.head(MAX_PER_CHECK + 1).itertuples():
        f.add(
            "keypoints",
            f"{row.image_id} crossing {row.crossing_id}: visibility {row.visibility} at ({row.u:.2f}, {row.v:.2f}) "
            f"is outside the {row.width}x{row.height} image",
        )
    counts = info.get("counts", {})
    for split in layout.SPLITS:
        n = int((s["split"] == split).sum())
        if split in counts and counts[split].get("images") != n:
            f.add("info", f"counts.{split}.images = {counts[split].get('images')} but samples has {n} rows")


def _check_yolo(path: Path, samples: pa.Table, f: Failures) -> None:
    s = samples.to_pydict()
    for iid, split in zip(s["image_id"], s["split"], strict=True):
        rel = layout.label_path(split, iid)
        p = path / rel
        if not p.exists():
            f.add("yolo", f"{rel} is missing")
            continue
        for n, line in enumerate(p.read_text().splitlines(), start=1):
            fields = line.split()
            if len(fields) != 8:
                f.add(
                    "yolo", f"{rel} line {n} has {len(fields)} fields; expected 8 (class cx cy w h px py v)"
                )
                continue
            try:
                vals = [float(x) for x in fields]
            except ValueError:
                f.add("yolo", f"{rel} line {n} has a field that is not a number")
                continue
            if vals[0] != 0:
                f.add("yolo", f"{rel} line {n}: class {fields[0]}; the only class is 0")
            if any(not (0.0 <= x <= 1.0) or math.isnan(x) for x in vals[1:7]):
                f.add("yolo", f"{rel} line {n}: coordinates outside [0, 1]")
            if vals[7] not in (0.0, 1.0, 2.0):
                f.add("yolo", f"{rel} line {n}: visibility {fields[7]}; accepted: 0, 1, 2")


def _check_coco(path: Path, samples: pa.Table | None, f: Failures) -> None:
    schema = json_schema("coco")
    ann_ids: dict[int, str] = {}
    img_ids: dict[int, str] = {}
    for split in layout.SPLITS:
        rel = layout.coco_path(split)
        p = path / rel
        if not p.exists():
            f.add("coco", f"{rel} is missing")
            continue
        try:
            d = json.loads(p.read_text())
        except json.JSONDecodeError as e:
            f.add("coco", f"{rel} is not valid JSON: {e}")
            continue
        errors = list(jsonschema.Draft202012Validator(schema).iter_errors(d))
        for err in errors[:MAX_PER_CHECK]:
            where = "/".join(str(x) for x in err.absolute_path) or "(top level)"
            f.add("coco", f"{rel} {where}: {err.message}")
        if errors:
            continue
        sizes = {}
        for im in d["images"]:
            if im["id"] in img_ids:
                f.add("coco", f"{rel}: image id {im['id']} also used in {img_ids[im['id']]}")
            img_ids[im["id"]] = rel
            sizes[im["id"]] = (im["width"], im["height"])
        for a in d["annotations"]:
            if a["id"] in ann_ids:
                f.add("coco", f"{rel}: duplicate annotation id {a['id']} (also in {ann_ids[a['id']]})")
            ann_ids[a["id"]] = rel
            if a["image_id"] not in sizes:
                f.add("coco", f"{rel}: annotation {a['id']} refers to unknown image {a['image_id']}")
                continue
            w, h = sizes[a["image_id"]]
            x, y, v = a["keypoints"]
            if v > 0 and not (0 <= x < w and 0 <= y < h):
                f.add(
                    "coco",
                    f"{rel}: annotation {a['id']} keypoint ({x:.2f}, {y:.2f}) is outside the {w}x{h} image",
                )
    if samples is not None and img_ids and len(img_ids) != samples.num_rows:
        f.add("coco", f"{len(img_ids)} COCO images but {samples.num_rows} samples")
