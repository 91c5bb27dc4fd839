"""``rebar dataset validate``: what every file of a dataset says, not only that its hash is the recorded one.

Checks, each failure one line ``<check>: <file> ...: <what is wrong>; expected <what would be right>``:

- contract: ``meta/info.json``, ``data.yaml`` and the COCO files against their JSON Schemas in
  ``schemas/``; the tables' columns and types against the field lists there;
- manifest: every file listed in ``meta/manifest.parquet`` with its size and sha256, and nothing else;
- content: every image, depth map (exact and sensor) and instance map decodes at its row's width and height
  with its type (RGB uint8 3 channels; depths and instances uint16 1 channel, 0 = no depth); every number of the tables, the YOLO files
  and the COCO files is finite and in its range (units and meanings in ``schemas/tables/``);
- references: every table row's files exist at their layout paths (both depth maps, from schema 2.3, or an
  instance map exactly when the config's ``dataset.store_depth``/``store_instances`` says so), every file
  under ``images/``, ``depth/``, ``sensor_depth/``, ``instances/`` and ``labels/`` belongs to a row,
  a sensor depth map's row names its model, keypoint rows to sample rows of the same split
  (one per crossing per image), COCO annotations to an image and a category of their file, COCO images to
  sample rows, and the tables' counts and image hashes to the keypoints table and the manifest.

Files other tools are known to add to a dataset folder (:data:`FOREIGN_FILES`) are reported as notes, never
as failures: a dataset someone trained on is still the dataset that was built, and ``rebar dataset
publish`` leaves them out. The images are decoded in a thread pool (OpenCV's decoder releases the GIL).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path, PurePosixPath

import cv2
import jsonschema
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import yaml

from rebar_data.config import ConfigError, parse_yaml
from rebar_data.dataset import layout
from rebar_data.dataset.layout import DatasetFormatError, DatasetInfo
from rebar_data.dataset.writers.manifest import listed_files
from rebar_data.digest import sha256_file

SCHEMA_DIR = Path(__file__).resolve().parents[2] / "schemas"
MAX_PER_CHECK = 5  # failures reported per check before summarising the rest
ROTATION_TOLERANCE = 1e-6  # largest |R R^T - I| entry of a camera pose's rotation

# Files other tools are known to write into a dataset folder, as globs relative to it: what writes each.
FOREIGN_FILES = {
    "labels/*.cache": "Ultralytics' label cache, written when it trains on the dataset",
    "images/*/*.npy": "Ultralytics' decoded-image cache, written when it trains with cache=disk",
}

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

# What each per-image file must decode to: the samples column naming it, dtype and channels.
_PICTURES = {
    "images": ("file_name", np.uint8, 3),
    "depth": ("depth_file", np.uint16, 1),
    "sensor_depth": ("sensor_depth_file", np.uint16, 1),
    "instances": ("instance_file", np.uint16, 1),
}


def field_list(table: str) -> list[dict]:
    return yaml.safe_load((SCHEMA_DIR / "tables" / f"{table}.yaml").read_text())["fields"]


def json_schema(name: str) -> dict:
    return json.loads((SCHEMA_DIR / f"{name}.schema.json").read_text())


def foreign_files(path: Path) -> dict[str, str]:
    """The files of the dataset at ``path`` that another tool added (:data:`FOREIGN_FILES`): relative POSIX
    path -> what wrote it."""
    path = Path(path)
    found = {}
    for pattern, what in FOREIGN_FILES.items():
        for p in path.glob(pattern):
            if p.is_file():
                found[p.relative_to(path).as_posix()] = what
    return dict(sorted(found.items()))


def is_foreign(rel: str) -> bool:
    """``rel`` (relative to a dataset folder) is a file another tool is known to add."""
    p = PurePosixPath(rel)
    return any(len(p.parts) == len(PurePosixPath(g).parts) and p.match(g) for g in FOREIGN_FILES)


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


def validate_dataset(path: Path, *, note: Callable[[str], None] = print) -> list[str]:
    """All contract violations of the dataset at ``path`` (empty when it is valid).

    Args:
        note: called with one line (``note: <file>: ...``) per file another tool added, which is not a
            violation; prints it by default.
    """
    path = Path(path)
    f = Failures()
    if not (path / layout.INFO).exists():
        f.add("layout", f"{layout.INFO} is missing; is {path} a dataset folder (<root>/<name>/v<version>)?")
        return f.lines
    foreign = foreign_files(path)
    for rel, what in foreign.items():
        note(f"note: {rel}: {what}; not part of the dataset (not checked, not published)")
    info_dict = _check_info(path, f)
    built = _schema_minor(info_dict)
    samples = _check_table(path, layout.SAMPLES, "samples", f, built)
    keypoints = _check_table(path, layout.KEYPOINTS, "keypoints", f, built)
    S = samples.to_pandas() if samples is not None else None
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        # the pictures decode in the pool (OpenCV releases the GIL) while this thread checks the rest
        decoding = _start_decoding(path, S, f, pool) if S is not None else []
        hashes = _check_manifest(path, f)
        _check_data_yaml(path, info_dict, f, note)
        if S is not None:
            _check_samples(S, info_dict, hashes, f)
            _check_unclaimed(path, S, foreign, f)
            _check_yolo(path, S, f)
        if S is not None and keypoints is not None:
            _check_keypoints(S, keypoints.to_pandas(), f)
        _check_coco(path, S, f)
        for job in decoding:
            problem = job.result()
            if problem:
                f.add(*problem)
    return f.lines


def _check_info(path: Path, f: Failures) -> dict:
    try:
        d = json.loads((path / layout.INFO).read_bytes())
    except (ValueError, OSError) as e:  # not JSON, not UTF-8 text (both ValueErrors), or unreadable
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


def _check_manifest(path: Path, f: Failures) -> dict[str, str]:
    """Checks the manifest and returns its path -> sha256 (empty when it is missing)."""
    if not (path / layout.MANIFEST).exists():
        f.add("manifest", f"{layout.MANIFEST} is missing")
        return {}
    man = pq.read_table(path / layout.MANIFEST).to_pydict()
    listed = dict(zip(man["path"], zip(man["bytes"], man["sha256"], strict=True), strict=True))

    def problem(rel: str, size: int, digest: str) -> str | None:
        p = path / rel
        if not p.exists():
            return f"{rel} is listed but missing"
        if p.stat().st_size != size or sha256_file(p) != digest:
            return f"{rel} does not match its sha256 in the manifest (changed since the build)"
        return None

    for rel, (size, digest) in listed.items():
        line = problem(rel, size, digest)
        if line:
            f.add("manifest", line)
    for rel in sorted(set(listed_files(path)) - set(listed)):
        if not is_foreign(rel):
            f.add("manifest", f"{rel} is not in the manifest")
    return {rel: digest for rel, (_, digest) in listed.items()}


# data.yaml keys a dataset of an earlier 2.x schema does not have: noted, not failed (the dataset was right
# when built); a rebuild adds them
DATA_YAML_SINCE = {"kpt_oks_sigmas": (2, 2), "flip_idx": (2, 2)}
# data.yaml's ``path``: before schema 2.4 the absolute folder it was built in (an absent one is accepted); from
# 2.4 there is none, so Ultralytics resolves the splits against the folder of data.yaml wherever it is copied
PATH_UNTIL = (2, 4)


def _schema_minor(info: dict) -> tuple[int, int]:
    try:
        major, minor = str(info.get("schema_version", "")).split(".")[:2]
        return int(major), int(minor)
    except ValueError:
        return (0, 0)


def _check_data_yaml(path: Path, info: dict, f: Failures, note: Callable[[str], None]) -> None:
    p = path / layout.DATA_YAML
    if not p.exists():
        f.add("data.yaml", "missing")
        return
    try:
        d = parse_yaml(p.read_bytes().decode("utf-8"), layout.DATA_YAML)
    except UnicodeDecodeError:
        f.add("data.yaml", "is not UTF-8 text; expected Ultralytics' YAML dataset file")
        return
    except ConfigError as e:  # not YAML, or aliases that expand without bound
        f.add("data.yaml", str(e).removeprefix(f"{layout.DATA_YAML}: "))
        return
    names = d.get("names") if isinstance(d, dict) else None
    if isinstance(names, dict):  # YAML reads the class ids as integers; JSON Schema keys are strings
        d = {**d, "names": {str(k): v for k, v in names.items()}}
    schema = json_schema("data_yaml")
    built = _schema_minor(info)
    older = [
        k for k, since in DATA_YAML_SINCE.items() if built < since and isinstance(d, dict) and k not in d
    ]
    if older:
        schema = {**schema, "required": [k for k in schema["required"] if k not in older]}
        note(
            f"note: data.yaml: no {' or '.join(older)} (schema {info.get('schema_version')}, before 2.2); "
            "Ultralytics then scores pose with its default sigma: rebuild the dataset, or add "
            f"kpt_oks_sigmas: [{info.get('oks_sigma')}] and flip_idx: [0]"
        )
    if built >= PATH_UNTIL and isinstance(d, dict) and "path" in d:
        f.add(
            "data.yaml",
            f"path = {d['path']!r}; expected no path (schema {info.get('schema_version')}: Ultralytics then "
            "takes the folder of data.yaml, wherever the dataset is copied)",
        )
    for err in sorted(jsonschema.Draft202012Validator(schema).iter_errors(d), key=str):
        where = "/".join(str(x) for x in err.absolute_path) or "(top level)"
        f.add("data.yaml", f"{where}: {err.message}")
    sigma = info.get("oks_sigma")
    if isinstance(d, dict) and "kpt_oks_sigmas" in d and d["kpt_oks_sigmas"] != [sigma]:
        f.add("data.yaml", f"kpt_oks_sigmas = {d['kpt_oks_sigmas']!r}; expected [{sigma}] (info.json)")


def _check_table(path: Path, rel: str, name: str, f: Failures, built: tuple[int, int]) -> pa.Table | None:
    """The table when it reads and has every listed column, each cast to its listed type for the value checks
    (a column of another type is a failure; one that does not cast leaves no table to check further). A
    field ``since`` a later schema than the dataset's (``built``) may be absent: it reads as nulls."""
    p = path / rel
    if not p.exists():
        f.add(name, f"{rel} is missing")
        return None
    try:
        t = pq.read_table(p)
    except (pa.ArrowInvalid, OSError) as e:
        f.add(name, f"{rel} is not a readable Parquet file: {e}")
        return None
    complete = True
    for fld in field_list(name):
        since = tuple(int(x) for x in str(fld.get("since", "0.0")).split("."))
        if fld["name"] not in t.column_names and built < since:
            t = t.append_column(fld["name"], pa.nulls(len(t), _TYPES[fld["type"]]))
            continue
        if fld["name"] not in t.column_names:
            f.add(name, f"column {fld['name']} is missing")
            complete = False
            continue
        want, got = _TYPES[fld["type"]], t.schema.field(fld["name"]).type
        if got != want:
            f.add(name, f"column {fld['name']} has type {got}; the schema says {fld['type']}")
            try:
                i = t.column_names.index(fld["name"])
                t = t.set_column(i, fld["name"], t[fld["name"]].cast(want))
            except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
                complete = False
    return t if complete else None


class _Column:
    """Reports rows of one table that break a rule, one line per column and rule."""

    def __init__(self, f: Failures, check: str, rel: str, df: pd.DataFrame, where: Callable[[int], str]):
        self.f, self.check, self.rel, self.df, self.where = f, check, rel, df, where

    def rule(self, col: str, bad, expected: str, *, what: str = "") -> None:
        bad = np.asarray(bad, bool)
        if not bad.any():
            return
        rows = np.flatnonzero(bad)
        i = int(rows[0])
        value = self.df[col].iloc[i]
        shown = _show(value, numeric=pd.api.types.is_numeric_dtype(self.df[col]))
        more = f" (and {len(rows) - 1} more rows)" if len(rows) > 1 else ""
        self.f.add(
            self.check,
            f"{self.rel} column {col}: {shown}{what} at row {i} ({self.where(i)}){more}; expected {expected}",
        )

    def finite(self, col: str, where=None, expected: str = "a finite number") -> np.ndarray:
        x = self.df[col].to_numpy(float)
        ok = np.isfinite(x)
        self.rule(col, ~ok if where is None else (~ok & where), expected)
        return ok


def _show(value, *, numeric: bool) -> str:
    if isinstance(value, float | np.floating) and numeric:
        return f"{float(value):.6g}"
    if isinstance(value, str):
        return repr(value)
    if value is None or (np.ndim(value) == 0 and pd.isna(value)):
        return "null"
    return str(value)


def _dataset_option(info: dict, key: str) -> bool:
    return bool(info.get("config", {}).get("dataset", {}).get(key, True))


def _check_samples(S: pd.DataFrame, info: dict, hashes: dict[str, str], f: Failures) -> None:
    rel = layout.SAMPLES
    ids = S["image_id"].astype(str).to_numpy()
    c = _Column(f, "samples", rel, S, lambda i: f"image {ids[i]}")
    dup = S["image_id"].duplicated().to_numpy()
    c.rule("image_id", dup, "unique image ids", what=" appears twice")
    c.rule("split", ~S["split"].isin(layout.SPLITS).to_numpy(), ", ".join(layout.SPLITS))
    for col in ("width", "height"):
        c.rule(col, ~(S[col].to_numpy(float) > 0), "> 0 (pixels)")
    for col in ("fx", "fy"):
        ok = c.finite(col)
        c.rule(col, ok & ~(S[col].to_numpy(float) > 0), "> 0 (pixels)")
    for col in ("cx", "cy"):
        c.finite(col)
    for col in ("frame", "sample_index", "n_visible", "n_occluded"):
        c.rule(col, ~(S[col].to_numpy(float) >= 0), ">= 0")
    _check_poses(c, S)
    for col in layout.randomized_columns(S.columns):
        if pd.api.types.is_bool_dtype(S[col]) or not pd.api.types.is_numeric_dtype(S[col]):
            c.rule(col, S[col].isna().to_numpy(), "a value")
            continue
        ok = c.finite(col)
        x = S[col].to_numpy(float)
        if col.endswith("_lux"):
            c.rule(col, ok & (x < 0), ">= 0 (an illuminance)")
        elif col.endswith("_k"):
            c.rule(col, ok & ~(x > 0), "> 0 (a colour temperature)")
    files = [layout.image_path(s, i) for s, i in zip(S["split"], ids, strict=True)]
    c.rule("file_name", S["file_name"].to_numpy() != np.array(files, object), "images/<split>/<image_id>.png")
    sensor_depth = _schema_minor(info) >= (2, 3)  # stored beside the depth maps since 2.3
    for col, key, template in (
        ("depth_file", "store_depth", layout.depth_path),
        *([("sensor_depth_file", "store_depth", layout.sensor_depth_path)] if sensor_depth else []),
        ("instance_file", "store_instances", layout.instance_path),
    ):
        want = [template(s, i) for s, i in zip(S["split"], ids, strict=True)]
        named = [g if isinstance(g, str) else None for g in S[col].to_numpy(object)]
        if _dataset_option(info, key):
            wrong = [g != w for g, w in zip(named, want, strict=True)]
            c.rule(col, wrong, f"{template('<split>', '<image_id>')} (dataset.{key} is true)")
        else:
            c.rule(col, [g is not None for g in named], f"null (dataset.{key} is false)")
    if "sensor_depth_model" in S.columns:
        from rebar_data.scene.config import DEPTH_MODELS

        named = S["sensor_depth_file"].notna().to_numpy()
        c.rule(
            "sensor_depth_model",
            named & ~S["sensor_depth_model"].isin(DEPTH_MODELS).to_numpy(),
            f"one of {', '.join(DEPTH_MODELS)}",
        )
    if hashes:
        listed = [hashes.get(p) for p in S["file_name"]]
        c.rule(
            "image_sha256",
            [h is not None and h != s for h, s in zip(listed, S["image_sha256"], strict=True)],
            f"the image's sha256 in {layout.MANIFEST}",
        )
    counts = info.get("counts", {})
    for split in layout.SPLITS:
        n = int((S["split"] == split).sum())
        if split in counts and counts[split].get("images") != n:
            f.add("info", f"counts.{split}.images = {counts[split].get('images')} but samples has {n} rows")


def _check_poses(c: _Column, S: pd.DataFrame) -> None:
    poses = S["world_from_camera"].to_numpy(object)
    bad_len = np.array([not hasattr(p, "__len__") or len(p) != 16 for p in poses], bool)
    c.rule("world_from_camera", bad_len, "16 numbers (a row-major 4x4 matrix)")
    if bad_len.any():
        return
    T = np.stack([np.asarray(p, float) for p in poses]).reshape(-1, 4, 4)
    finite = np.isfinite(T).all(axis=(1, 2))
    c.rule("world_from_camera", ~finite, "16 finite numbers", what=" (not finite)")
    R = T[:, :3, :3]
    err = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    rigid = (np.abs(T[:, 3] - [0, 0, 0, 1]).max(axis=1) == 0) & (err <= ROTATION_TOLERANCE)
    c.rule(
        "world_from_camera", finite & ~rigid, "a rigid transform (bottom row 0 0 0 1, orthonormal rotation)"
    )


def _start_decoding(path: Path, S: pd.DataFrame, f: Failures, pool: ThreadPoolExecutor) -> list[Future]:
    """Every file a row names exists (checked now) and decodes at the row's size with its type (checked by
    the returned futures: each gives ``(check, detail)`` or None)."""
    jobs = []
    for row in S.itertuples(index=False):
        for check, (col, dtype, channels) in _PICTURES.items():
            rel = getattr(row, col)
            if not isinstance(rel, str):
                continue  # null: whether it may be is _check_samples' concern
            if not (path / rel).is_file():
                f.add(
                    check, f"{rel} is missing; expected the {col} of row {row.image_id} in {layout.SAMPLES}"
                )
                continue
            want = (int(row.width), int(row.height), np.dtype(dtype).name, channels)
            jobs.append(pool.submit(_decode, check, path / rel, rel, want))
    return jobs


def _decode(check: str, p: Path, rel: str, want: tuple[int, int, str, int]) -> tuple[str, str] | None:
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    expected = f"{want[0]}x{want[1]} {want[2]} {_channels(want[3])}"
    if img is None:
        return check, f"{rel} does not decode; expected a PNG of {expected}"
    got = (img.shape[1], img.shape[0], img.dtype.name, 1 if img.ndim == 2 else img.shape[2])
    if got != want:
        shown = f"{got[0]}x{got[1]} {got[2]} {_channels(got[3])}"
        return check, f"{rel} is {shown}; expected {expected} ({layout.SAMPLES} width, height)"
    return None


def _channels(n: int) -> str:
    return f"{n} channel" + ("s" if n != 1 else "")


def _check_unclaimed(path: Path, S: pd.DataFrame, foreign: dict[str, str], f: Failures) -> None:
    """Every file under the per-image folders belongs to a row of the samples table."""
    claimed = {
        "images": set(S["file_name"]),
        "depth": set(S["depth_file"].dropna()),
        "sensor_depth": set(S["sensor_depth_file"].dropna()),
        "instances": set(S["instance_file"].dropna()),
        "labels": {layout.label_path(s, i) for s, i in zip(S["split"], S["image_id"], strict=True)},
    }
    for folder, own in claimed.items():
        if not (path / folder).is_dir():
            continue
        for p in sorted((path / folder).rglob("*")):
            rel = p.relative_to(path).as_posix()
            if p.is_file() and rel not in own and rel not in foreign:
                f.add(folder, f"{rel} has no row in {layout.SAMPLES}; expected only the files its rows name")


def _check_keypoints(S: pd.DataFrame, K: pd.DataFrame, f: Failures) -> None:
    rel = layout.KEYPOINTS
    iid = K["image_id"].astype(str).to_numpy()
    cid = K["crossing_id"].to_numpy()
    c = _Column(f, "keypoints", rel, K, lambda i: f"image {iid[i]}, crossing {cid[i]}")
    samples = S.drop_duplicates("image_id").set_index("image_id")
    known = K["image_id"].isin(samples.index).to_numpy()
    c.rule("image_id", ~known, f"an image_id of {layout.SAMPLES}")
    split = K["image_id"].map(samples["split"])
    c.rule("split", known & (K["split"] != split).to_numpy(), f"the image's split in {layout.SAMPLES}")
    c.rule(
        "crossing_id",
        K.duplicated(["image_id", "crossing_id"]).to_numpy(),
        "one row per crossing per image",
        what=" appears twice",
    )
    for col in ("crossing_id", "bar_a", "bar_b"):
        c.rule(col, ~(K[col].to_numpy(float) >= 0), ">= 0")
    c.rule("layer", ~(K["layer"].to_numpy(float) >= -1), ">= -1 (-1: bars of two mats, from IFC)")
    c.rule("hit_instance", ~(K["hit_instance"].to_numpy(float) >= -3), ">= -3")
    c.rule("tie_wire", K["tie_wire"].isna().to_numpy(), "true or false")
    vis = K["visibility"].to_numpy(float)
    c.rule("visibility", ~np.isin(vis, (0, 1, 2)), "0, 1 or 2 (outside, occluded, visible)")
    for col in ("x_world", "y_world", "z_world", "x_crossing", "y_crossing", "z_crossing"):
        c.finite(col, expected="a finite number (metres)")
    depth_ok = c.finite("depth_m", expected="a finite number (metres)")
    depth = K["depth_m"].to_numpy(float)
    box = K["box_size_px"].to_numpy(float)
    shown = vis > 0
    c.rule("depth_m", depth_ok & shown & ~(depth > 0), "> 0 for a keypoint in view (visibility 1 or 2)")
    box_ok = c.finite("box_size_px", expected="a finite number (pixels)")
    c.rule("box_size_px", box_ok & ~(box >= 0), ">= 0")
    c.rule("box_size_px", box_ok & (depth > 0) & ~(box > 0), "> 0 in front of the camera (depth_m > 0)")
    in_front = depth > 0
    for col in ("u", "v"):
        x = K[col].to_numpy(float)
        c.rule(col, np.isinf(x), "a finite number, or NaN behind the camera")
        c.rule(col, np.isnan(x) & in_front, "a finite number in front of the camera (depth_m > 0)")
    size = (
        K["image_id"].map(samples["width"]).to_numpy(float),
        K["image_id"].map(samples["height"]).to_numpy(float),
    )
    u, v = K["u"].to_numpy(float), K["v"].to_numpy(float)
    outside = known & shown & ~((u >= 0) & (u < size[0]) & (v >= 0) & (v < size[1]))
    for i in np.flatnonzero(outside)[: MAX_PER_CHECK + 1]:
        f.add(
            "keypoints",
            f"{iid[i]} crossing {cid[i]}: visibility {int(vis[i])} at ({u[i]:.2f}, {v[i]:.2f}) is outside the "
            f"{int(size[0][i])}x{int(size[1][i])} image; expected a point inside it",
        )
    per_image = K.groupby("image_id").size().reindex(samples.index, fill_value=0)
    want = int(per_image.max()) if len(per_image) else 0
    for image_id, n in per_image[per_image != want].head(MAX_PER_CHECK + 1).items():
        f.add(
            "keypoints",
            f"{rel}: image {image_id} has {n} rows; expected {want} (one per crossing of the mesh)",
        )
    counted = K[known].groupby(["image_id", "visibility"]).size().unstack(fill_value=0)
    sc = _Column(f, "samples", layout.SAMPLES, S, lambda i: f"image {S['image_id'].iloc[i]}")
    for col, level in (("n_visible", 2), ("n_occluded", 1)):
        n = S["image_id"].map(counted.get(level, {})).fillna(0).to_numpy(int)
        sc.rule(col, S[col].to_numpy(float) != n, f"the image's rows of visibility {level} in {rel}")


def _check_yolo(path: Path, S: pd.DataFrame, f: Failures) -> None:
    for iid, split in zip(S["image_id"], S["split"], strict=True):
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
            elif not (vals[3] > 0 and vals[4] > 0):
                f.add(
                    "yolo", f"{rel} line {n}: box {fields[3]} x {fields[4]}; expected a width and height > 0"
                )
            if vals[7] not in (0.0, 1.0, 2.0):
                f.add("yolo", f"{rel} line {n}: visibility {fields[7]}; accepted: 0, 1, 2")


def _check_coco(path: Path, S: pd.DataFrame | None, f: Failures) -> None:
    schema = json_schema("coco")
    rows = S.drop_duplicates("file_name").set_index("file_name") if S is not None else None
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
        categories = sorted(c["id"] for c in d["categories"])
        sizes = {}
        for im in d["images"]:
            if im["id"] in img_ids:
                f.add("coco", f"{rel}: image id {im['id']} also used in {img_ids[im['id']]}")
            img_ids[im["id"]] = rel
            sizes[im["id"]] = (im["width"], im["height"])
            _check_coco_image(rel, split, im, rows, f)
        for a in d["annotations"]:
            if a["id"] in ann_ids:
                f.add("coco", f"{rel}: duplicate annotation id {a['id']} (also in {ann_ids[a['id']]})")
            ann_ids[a["id"]] = rel
            if a["category_id"] not in categories:
                f.add(
                    "coco",
                    f"{rel}: annotation {a['id']} has category {a['category_id']}; expected one of "
                    f"{', '.join(map(str, categories))} (the file's categories)",
                )
            numbers = {"keypoints": a["keypoints"], "bbox": a["bbox"], "area": [a["area"]]}
            broken = [k for k, vs in numbers.items() if not all(math.isfinite(x) for x in vs)]
            if broken:
                f.add(
                    "coco",
                    f"{rel}: annotation {a['id']} {broken[0]} {numbers[broken[0]]}; expected finite numbers",
                )
                continue
            if not (a["bbox"][2] > 0 and a["bbox"][3] > 0):
                f.add(
                    "coco", f"{rel}: annotation {a['id']} bbox {a['bbox']}; expected a width and height > 0"
                )
            if a["image_id"] not in sizes:
                f.add(
                    "coco",
                    f"{rel}: annotation {a['id']} refers to unknown image {a['image_id']}; expected an image id "
                    "of the file's images",
                )
                continue
            w, h = sizes[a["image_id"]]
            x, y, v = a["keypoints"]
            if v not in (0, 1, 2):
                f.add("coco", f"{rel}: annotation {a['id']} keypoint visibility {v}; expected 0, 1 or 2")
            elif v > 0 and not (0 <= x < w and 0 <= y < h):
                f.add(
                    "coco",
                    f"{rel}: annotation {a['id']} keypoint ({x:.2f}, {y:.2f}) is outside the {w}x{h} image",
                )
    if S is not None and img_ids and len(img_ids) != len(S):
        f.add("coco", f"{len(img_ids)} COCO images but {len(S)} samples")


def _check_coco_image(rel: str, split: str, im: dict, rows: pd.DataFrame | None, f: Failures) -> None:
    if rows is None:
        return
    name = im["file_name"]
    if name not in rows.index:
        f.add("coco", f"{rel}: image {im['id']} file_name {name!r} has no row in {layout.SAMPLES}")
        return
    row = rows.loc[name]
    if row["split"] != split:
        f.add("coco", f"{rel}: image {im['id']} ({name}) is in split {row['split']} in {layout.SAMPLES}")
    if (im["width"], im["height"]) != (row["width"], row["height"]):
        f.add(
            "coco",
            f"{rel}: image {im['id']} ({name}) is {im['width']}x{im['height']}; expected "
            f"{row['width']}x{row['height']} ({layout.SAMPLES})",
        )
