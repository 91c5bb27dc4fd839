"""The on-disk dataset format: path templates, the schema version and the typed ``meta/info.json``.

A reader refuses a dataset whose major schema version it does not know, and warns (does not fail) on
unknown keys in info.json, so newer minor versions stay readable.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

# 2.1: info.json records the renderer; 2.2: data.yaml has kpt_oks_sigmas and flip_idx; 2.3: sensor_depth/
# beside depth/, with the samples table's sensor_depth_file and sensor_depth_* columns; 2.4: data.yaml has no
# path (Ultralytics takes the file's own folder, wherever the dataset is copied)
SCHEMA_VERSION = "2.4.0"
SPLITS = ("train", "val", "test")
INSTANCE_OFFSET = 3  # instance maps store id + 3: 0 distractor, 1 surroundings, 2 nothing, 3+ rebar parts
KEYPOINT_NAMES = ["intersection"]
CATEGORY = "rebar_crossing"

INFO = "meta/info.json"
MANIFEST = "meta/manifest.parquet"
MESH_IFC = "meta/mesh.ifc"  # a mesh read from IFC: the model it was read from, which the audit reads again
DATA_YAML = "data.yaml"
SAMPLES = "tables/samples.parquet"
KEYPOINTS = "tables/keypoints.parquet"
AUDIT_DIR = "audit"
# The samples table's randomized columns (beyond its field list): lights, materials, surroundings, sensor.
RANDOMIZED_PREFIXES = ("light_", "mat_", "surr_", "sensor_")
# listed columns that carry a randomized prefix but name a file
FILE_COLUMNS = ("sensor_depth_file",)


def randomized_columns(columns) -> list[str]:
    """The samples table's randomized columns among ``columns`` (a prefix of RANDOMIZED_PREFIXES, not a file)."""
    return [c for c in columns if c.startswith(RANDOMIZED_PREFIXES) and c not in FILE_COLUMNS]


def image_path(split: str, image_id: str) -> str:
    return f"images/{split}/{image_id}.png"


def label_path(split: str, image_id: str) -> str:
    return f"labels/{split}/{image_id}.txt"


def depth_path(split: str, image_id: str) -> str:
    return f"depth/{split}/{image_id}.png"


def sensor_depth_path(split: str, image_id: str) -> str:
    return f"sensor_depth/{split}/{image_id}.png"


def instance_path(split: str, image_id: str) -> str:
    return f"instances/{split}/{image_id}.png"


def coco_path(split: str) -> str:
    return f"annotations/{split}.json"


def mesh_sections(ds: Path, config: dict) -> dict:
    """The mesh sections (seed, mesh, realism, pose) of a dataset's recorded config; a mesh read from IFC
    reads the dataset's own copy of the model (``meta/mesh.ifc``) when it has one."""
    keys = {k: config[k] for k in ("seed", "mesh", "realism", "pose") if k in config}
    mesh = keys.get("mesh")
    if isinstance(mesh, dict) and mesh.get("kind") == "ifc" and (Path(ds) / MESH_IFC).is_file():
        keys["mesh"] = {**mesh, "ifc_path": str((Path(ds) / MESH_IFC).resolve())}
    return keys


def dataset_dir(root: Path, name: str, version: str) -> Path:
    return Path(root) / name / f"v{version}"


class DatasetFormatError(Exception):
    """A dataset on disk cannot be read by this version of the toolkit."""


def read_table(path: Path):
    """A dataset's Parquet table (``pyarrow.Table``); a file cut short or not Parquet is a
    ``DatasetFormatError`` naming it."""
    import pyarrow.parquet as pq

    try:
        return pq.read_table(path)
    except (OSError, ValueError) as e:  # pyarrow's ArrowIOError and ArrowInvalid
        raise DatasetFormatError(
            f"{path}: cannot be read as a Parquet table ({' '.join(str(e).split())[:160]}); expected the table "
            "`rebar dataset build` writes (rebuild the dataset, or restore the file)"
        ) from None


@dataclass
class DatasetInfo:
    """Everything ``meta/info.json`` holds: identity, provenance, counts and label conventions."""

    name: str
    version: str
    schema_version: str
    generator: dict  # {"name", "version", "git_commit"}
    config: dict  # the resolved pipeline config
    config_hash: str
    seed: int
    counts: dict  # per split: images, keypoints (all rows), visible, occluded
    split: dict  # {"rule", "fractions", "groups": {split: [ids]}}
    image_size: dict  # {"width", "height"}
    intrinsics: dict  # {"fx", "fy", "cx", "cy", "convention"}
    keypoint_names: list[str]
    oks_sigma: float
    oks_area: str
    conventions: dict
    description: str = ""
    renderer: dict = field(default_factory=dict)  # {"engine", its version, settings}; absent before 2.1
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = asdict(self)
        extra = d.pop("extra")
        if not d["renderer"]:
            d.pop("renderer")
        d.update(extra)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> DatasetInfo:
        if not isinstance(d, dict):
            raise DatasetFormatError(f"{INFO}: the top level is {type(d).__name__}; expected a JSON object")
        major = str(d.get("schema_version", "0")).split(".")[0]
        if major != SCHEMA_VERSION.split(".")[0]:
            raise DatasetFormatError(
                f"schema_version {d.get('schema_version')!r} is not readable by this toolkit "
                f"(reads {SCHEMA_VERSION.split('.')[0]}.x)"
            )
        known = {f.name for f in fields(cls)} - {"extra"}
        unknown = sorted(set(d) - known)
        if unknown:
            warnings.warn(
                f"info.json has keys this toolkit does not know: {', '.join(unknown)}", stacklevel=2
            )
        return cls(**{k: d[k] for k in known if k in d}, extra={k: d[k] for k in unknown})

    def write(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n")

    @classmethod
    def read(cls, dataset: Path) -> DatasetInfo:
        p = Path(dataset) / INFO
        if not p.exists():
            raise DatasetFormatError(
                f"{dataset}: no {INFO}; is this a dataset folder (<root>/<name>/v<version>)?"
            )
        try:
            data = json.loads(p.read_bytes())
        except OSError as e:
            raise DatasetFormatError(f"{p}: cannot be read ({e.strerror})") from None
        except ValueError as e:  # cut short, not JSON, or not UTF-8 text
            raise DatasetFormatError(
                f"{p}: not valid JSON ({e}); expected the info file `rebar dataset build` writes (rebuild the "
                "dataset, or restore the file)"
            ) from None
        try:
            return cls.from_dict(data)
        except DatasetFormatError as e:
            raise DatasetFormatError(f"{dataset}: {e}") from None
        except TypeError as e:  # a key the class needs is missing
            raise DatasetFormatError(
                f"{p}: {e}; expected the info file `rebar dataset build` writes"
            ) from None
