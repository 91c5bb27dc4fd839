"""Reads a dataset in the project's layout (the contract in docs/datasets.md) into per-image keypoint records: the
images of a split from ``tables/samples.parquet``, their crossings from ``tables/keypoints.parquet`` and the
OKS sigma from ``meta/info.json``. Visible crossings (visibility 2) are what the detector learns and is
scored on; occluded ones (visibility 1) are kept apart so training can leave them out of the loss."""

from __future__ import annotations

import json
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cache
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np
import pyarrow.parquet as pq

from rebar_data.camera import Intrinsics
from rebar_data.config import ConfigError
from rebar_data.dataset import layout
from rebar_data.dataset.layout import SPLITS
from rebar_data.perception.inference.checks import MM_PER_M
from rebar_data.pipeline import DEFAULT_OKS_SIGMA
from rebar_data.scene.config import DEPTH_MODELS

T = TypeVar("T")

_SAMPLE_COLUMNS = ("image_id", "split", "file_name", "width", "height", "fx", "fy", "cx", "cy")
_KEYPOINT_COLUMNS = ("image_id", "u", "v", "visibility", "box_size_px")
# a crossing's pixel: ``sight``, the dataset's u, v (where the image shows the bars cross), or ``crossing``,
# the projected 3D crossing point (inside the steel), as labels made from the 3D point alone place it
TRUTHS = ("sight", "crossing")
_CROSSING_COLUMNS = ("x_crossing", "y_crossing", "z_crossing")


@dataclass
class Sample:
    """One image and its crossings, in pixels with COCO's corner origin: (N, 2) visible ones with each one's
    detection-box side (its OKS scale), (M, 2) occluded ones (inside the image but hidden), the intrinsics
    (fx, fy, cx, cy), the registered exact depth image, the depth sensor's image (datasets from 2.3.0) and
    the instance map (None where the dataset has none), and ``crossings``, the projected 3D crossing point
    of each visible one (NaN where not recorded; None when the dataset's tables lack the 3D points)."""

    image_id: str
    path: Path
    width: int
    height: int
    visible: np.ndarray
    box_size_px: np.ndarray
    occluded: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    occluded_box_size_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    camera: tuple[float, float, float, float] | None = None
    depth_path: Path | None = None
    sensor_depth_path: Path | None = None
    crossings: np.ndarray | None = None
    dataset: Path | None = None
    instance_path: Path | None = None

    @property
    def intrinsics(self) -> Intrinsics | None:
        """``camera`` as the image's :class:`~rebar_data.camera.Intrinsics` (None without one)."""
        return None if self.camera is None else Intrinsics(self.width, self.height, *self.camera)


def read_image(path: str | Path) -> np.ndarray:
    """An image file as RGB uint8 (H, W, 3)."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ConfigError(f"{path}: cannot be read as an image; accepted: a PNG or JPEG file")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def read_uint16(path: str | Path, what: str) -> np.ndarray:
    """A 16-bit PNG as it is stored; ``what`` names what was expected."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ConfigError(f"{path}: cannot be read; accepted: {what}")
    return image


def read_distractors(sample: Sample) -> np.ndarray | None:
    """(H, W) bool: where the sample's instance map shows a distractor (the lower mat, spacers, loose tie
    wire, formwork: one id, ``DISTRACTOR_ID``); None when the dataset has no instance map."""
    if sample.instance_path is None:
        return None
    from rebar_data.scene.surroundings import DISTRACTOR_ID

    return (
        read_uint16(sample.instance_path, "a 16-bit instance PNG") == DISTRACTOR_ID + layout.INSTANCE_OFFSET
    )


def per_file(samples: list[Sample], read: Callable[[Sample], T]) -> list[T]:
    """``read`` of each sample, called once per file (a file listed again shares the first call's result)."""
    of = per_file_lazily(samples, read)
    return [of(i) for i in range(len(samples))]


def per_file_lazily(samples: list[Sample], read: Callable[[Sample], T]) -> Callable[[int], T]:
    """:func:`per_file` called when first asked for: ``read`` of sample ``i``, once per file."""
    done: dict[str, T] = {}

    def of(i: int) -> T:
        key = str(samples[i].path)
        if key not in done:
            done[key] = read(samples[i])
        return done[key]

    return of


def read_sample_image(sample: Sample) -> np.ndarray:
    """The sample's RGB image (:func:`read_image` of its path)."""
    return read_image(sample.path)


# the depth a detector reads: the dataset's sensor depth (else its exact depth), the exact depth, or a depth
# sensor model's image of the exact depth (its nominal parameters, 1 px off the colour)
DEPTH_SOURCES = ("sensor", *DEPTH_MODELS)


@cache
def _nominal_sensor(model: str):
    """The sensor ``model`` as :func:`sample_depth` simulates it, built once per model."""
    from rebar_data.scene.sample import nominal_depth_sensor

    return replace(nominal_depth_sensor(model), shift_x_px=1.0)


def check_depth_source(source: str, given: str) -> None:
    """Raise ConfigError, naming what was ``given``, unless ``source`` is one of :data:`DEPTH_SOURCES`."""
    if source not in DEPTH_SOURCES:
        raise ConfigError(f"{given}: not a depth source; accepted: one of {', '.join(DEPTH_SOURCES)}")


def sample_depth(s: Sample, source: str = "sensor") -> np.ndarray | None:
    """The depth image (float32 metres, 0 = none) that ``source`` (see :data:`DEPTH_SOURCES`) gives for ``s``;
    None when the dataset has no depth. A sensor model's noise is drawn from the image id alone."""
    check_depth_source(source, f"depth source {source!r}")
    if source == "sensor" and s.sensor_depth_path is not None:
        return read_depth(s.sensor_depth_path, size=(s.width, s.height))
    if s.depth_path is None:
        return None
    exact = read_depth(s.depth_path, size=(s.width, s.height))
    if source in ("sensor", "exact"):
        return exact
    from rebar_data.render.depth_sensor import sense_depth

    rng = np.random.default_rng(zlib.crc32(s.image_id.encode()))
    return sense_depth(exact, _nominal_sensor(source), rng, fx=s.camera[0])


def read_depth(path: str | Path, *, size: tuple[int, int] | None = None) -> np.ndarray:
    """A dataset's depth image (uint16 millimetres of camera z, 0 = no measurement) as float32 metres;
    ``size`` (width, height), when given, is the size it must have (its colour image's)."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.ndim != 2 or raw.dtype != np.uint16:
        raise ConfigError(
            f"{path}: cannot be read as a depth image; accepted: a one-channel 16-bit PNG of millimetres"
        )
    if size is not None and raw.shape != (size[1], size[0]):
        raise ConfigError(
            f"{path}: a depth image of {raw.shape[1]}x{raw.shape[0]} px; accepted: one of its colour image's "
            f"size, {size[0]}x{size[1]} px (the samples table's width and height)"
        )
    return raw.astype(np.float32) / MM_PER_M


def read_images(samples: list[Sample]) -> list[np.ndarray]:
    """Each sample's image, decoded once per file (:func:`per_file`)."""
    return per_file(samples, read_sample_image)


def read_info(root: str | Path) -> dict:
    """The dataset's ``meta/info.json`` (an empty dict when it has none)."""
    p = Path(root) / "meta/info.json"
    if not p.exists():
        return {}
    try:
        info = json.loads(p.read_bytes())
    except ValueError as e:  # cut short, not JSON, or not UTF-8 text
        raise ConfigError(
            f"{p}: not valid JSON ({e}); expected the info file `rebar dataset build` writes (rebuild the "
            "dataset, or restore the file)"
        ) from None
    if not isinstance(info, dict):
        raise ConfigError(f"{p}: the top level is {type(info).__name__}; expected a JSON object")
    return info


def renderer_engine(info: dict) -> str:
    """The engine that rendered a dataset, from its info.json (none named before schema 2.1: Open3D)."""
    return (info.get("renderer") or {}).get("engine", "open3d")


def stated_oks_sigma(root: str | Path) -> float:
    """The OKS sigma the dataset states in its info.json (the project's default when it states none)."""
    return float(read_info(root).get("oks_sigma", DEFAULT_OKS_SIGMA))


def check_dataset(root: str | Path) -> Path:
    """Return ``root`` as a Path if it holds the two tables the detector reads, else raise ConfigError."""
    root = Path(root)
    accepted = "accepted: a dataset folder written by `rebar dataset build` (ROOT/<name>/v<version>/)"
    if not root.is_dir():
        raise ConfigError(f"{root}: no such dataset folder; {accepted}")
    for t in ("tables/samples.parquet", "tables/keypoints.parquet"):
        if not (root / t).exists():
            raise ConfigError(f"{root}: has no {t}; {accepted}")
    return root


def load_split(root: str | Path, split: str, *, truth: str = "sight") -> list[Sample]:
    """Every image of ``split`` with its visible and occluded crossings, in the samples table's order;
    ``truth`` says which pixel stands for a crossing (see ``TRUTHS``)."""
    root = check_dataset(root)
    if split not in SPLITS:
        raise ConfigError(f"split = {split!r} is not accepted; accepted: one of {', '.join(SPLITS)}")
    if truth not in TRUTHS:
        raise ConfigError(f"truth = {truth!r} is not accepted; accepted: one of {', '.join(TRUTHS)}")
    samples = pq.read_table(root / "tables/samples.parquet").to_pydict()
    _require(samples, _SAMPLE_COLUMNS, root / "tables/samples.parquet")
    kp = pq.read_table(root / "tables/keypoints.parquet").to_pydict()
    _require(kp, _KEYPOINT_COLUMNS, root / "tables/keypoints.parquet")
    ids = np.asarray(kp["image_id"]).astype(str)
    sight = np.c_[np.asarray(kp["u"], float), np.asarray(kp["v"], float)]
    has_points = all(c in kp for c in _CROSSING_COLUMNS) and "world_from_camera" in samples
    points = _projected_crossings(root, samples, kp, ids) if has_points or truth == "crossing" else None
    uv = points if truth == "crossing" else sight
    vis = np.asarray(kp["visibility"], int)
    box = np.asarray(kp["box_size_px"], float)
    order = np.argsort(ids, kind="stable")
    sorted_ids = ids[order]
    out = []
    for i, s in enumerate(samples["split"]):
        if s != split:
            continue
        iid = samples["image_id"][i]
        lo, hi = np.searchsorted(sorted_ids, iid, "left"), np.searchsorted(sorted_ids, iid, "right")
        rows = order[lo:hi]
        v = vis[rows]
        depth = root / layout.depth_path(split, iid)
        sensor = root / layout.sensor_depth_path(split, iid)
        instances = root / layout.instance_path(split, iid)
        out.append(
            Sample(
                image_id=iid,
                path=root / samples["file_name"][i],
                width=int(samples["width"][i]),
                height=int(samples["height"][i]),
                visible=uv[rows][v == 2],
                box_size_px=box[rows][v == 2],
                occluded=uv[rows][v == 1],
                occluded_box_size_px=box[rows][v == 1],
                camera=tuple(float(samples[k][i]) for k in ("fx", "fy", "cx", "cy")),
                depth_path=depth if depth.exists() else None,
                sensor_depth_path=sensor if sensor.exists() else None,
                crossings=points[rows][v == 2] if points is not None else None,
                dataset=root,
                instance_path=instances if instances.exists() else None,
            )
        )
    return out


def _projected_crossings(root: Path, samples: dict, kp: dict, ids: np.ndarray) -> np.ndarray:
    """(N, 2) pixel of each keypoint row's 3D crossing point, projected with its image's camera."""
    _require(samples, ("world_from_camera",), root / "tables/samples.parquet")
    _require(kp, _CROSSING_COLUMNS, root / "tables/keypoints.parquet")
    row = {iid: i for i, iid in enumerate(samples["image_id"])}
    index = np.array([row[i] for i in ids], int)
    camera_from_world = np.linalg.inv(np.asarray(samples["world_from_camera"], float).reshape(-1, 4, 4))
    k = {c: np.asarray(samples[c], float)[index] for c in ("fx", "fy", "cx", "cy")}
    xyz = np.c_[[np.asarray(kp[c], float) for c in _CROSSING_COLUMNS]].T
    cam = np.einsum("nij,nj->ni", camera_from_world[index, :3, :3], xyz) + camera_from_world[index, :3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.c_[k["fx"] * cam[:, 0] / cam[:, 2] + k["cx"], k["fy"] * cam[:, 1] / cam[:, 2] + k["cy"]]


def _require(table: dict, columns: tuple[str, ...], path: Path) -> None:
    missing = [c for c in columns if c not in table]
    if missing:
        raise ConfigError(f"{path}: lacks column {missing[0]}; accepted: a table with {', '.join(columns)}")
