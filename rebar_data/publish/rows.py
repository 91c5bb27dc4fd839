"""Ready-to-train rows: Parquet shards in the Hugging Face ``datasets`` layout with the images embedded.

One row per image: the PNG itself (a ``datasets`` Image feature, a struct of ``bytes`` and ``path``),
the camera (intrinsics and pose), where the frame comes from (scene, trajectory) and every crossing in
the image (visibility 1 or 2) with its pixel position, visibility, box and 3D point. Shards are named
``data/<split>-NNNNN-of-MMMMM.parquet`` with the dataset's own split names, ``train``, ``val`` and ``test``,
the names every other view of the bundle uses (the card's ``configs`` declare them to ``datasets``).
The schema carries ``datasets``' feature metadata for the image column, so ``datasets`` decodes it to a
PIL image while every other column is read as its Arrow type.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from rebar_data.dataset import layout
from rebar_data.dataset.writers.yolo import clipped_box

DATA_DIR = "data"
SHARD_MAX_BYTES = 256 * 1024 * 1024  # image bytes per shard; the Hub's viewer and loaders like < 500 MB
ROW_GROUP_ROWS = 64

KEYPOINT_FIELDS = [
    ("crossing_id", pa.int32(), "crossing of the mesh (same id in every image)"),
    ("u", pa.float64(), "projected x in pixels, COCO corner origin (u = fx x / z + cx)"),
    ("v", pa.float64(), "projected y in pixels, COCO corner origin"),
    ("visibility", pa.int8(), "1 inside the image but occluded, 2 visible"),
    (
        "bbox",
        pa.list_(pa.float64()),
        "COCO box [x, y, width, height] in pixels, the square clipped to the image",
    ),
    ("box_size_px", pa.float64(), "side of the unclipped square box; box_size_px ** 2 is the OKS area"),
    ("depth_m", pa.float64(), "camera-frame z of the sight point in metres"),
    (
        "x_world",
        pa.float64(),
        "sight point the keypoint projects from (on the nearer bar), world frame, metres",
    ),
    (
        "y_world",
        pa.float64(),
        "sight point the keypoint projects from (on the nearer bar), world frame, metres",
    ),
    (
        "z_world",
        pa.float64(),
        "sight point the keypoint projects from (on the nearer bar), world frame, metres",
    ),
    ("tie_wire", pa.bool_(), "the crossing has a tie-wire loop"),
]
KEYPOINT_TYPE = pa.struct([(n, t) for n, t, _ in KEYPOINT_FIELDS])
IMAGE_TYPE = pa.struct([("bytes", pa.binary()), ("path", pa.string())])

ROW_FIELDS = [
    ("image", IMAGE_TYPE, "the RGB image (PNG bytes and file name); datasets decodes it to a PIL image"),
    ("image_id", pa.string(), "unique id, <trajectory_id>-f<frame>; the stem of the image file"),
    ("file_name", pa.string(), "the image's path in this bundle (the YOLO and COCO views use it)"),
    ("width", pa.int32(), "image width in pixels"),
    ("height", pa.int32(), "image height in pixels"),
    ("fx", pa.float64(), "focal length in x, pixels"),
    ("fy", pa.float64(), "focal length in y, pixels"),
    ("cx", pa.float64(), "principal point x, pixels, COCO corner origin"),
    ("cy", pa.float64(), "principal point y, pixels, COCO corner origin"),
    ("world_from_camera", pa.list_(pa.float64()), "row-major 4x4 pose of the OpenCV camera in the world (m)"),
    ("scene_id", pa.string(), "scene (lights, material, surroundings) of the image"),
    ("trajectory_id", pa.string(), "camera trajectory of the image"),
    ("trajectory_kind", pa.string(), "kind of camera trajectory"),
    ("frame", pa.int32(), "index of the frame along its trajectory"),
    ("n_visible", pa.int32(), "crossings with visibility 2"),
    ("n_occluded", pa.int32(), "crossings with visibility 1"),
    (
        "keypoints",
        pa.list_(KEYPOINT_TYPE),
        "every crossing inside the image (visibility 1 or 2), by crossing_id",
    ),
]
ROW_SCHEMA = pa.schema([(n, t) for n, t, _ in ROW_FIELDS]).with_metadata(
    {"huggingface": json.dumps({"info": {"features": {"image": {"_type": "Image"}}}})}
)


@dataclass(frozen=True)
class Shard:
    path: str  # relative to the bundle
    split: str  # train, val or test
    rows: int


def _keypoints_by_image(keypoints: pa.Table) -> dict[str, list[dict]]:
    k = keypoints.to_pandas()
    k = k[k.visibility > 0].sort_values(["image_id", "crossing_id"])
    out: dict[str, list[dict]] = {}
    for row in k.itertuples(index=False):
        out.setdefault(row.image_id, []).append(row)
    return out


def _row(s: dict, kps: list, image: bytes) -> dict:
    w, h = int(s["width"]), int(s["height"])
    points = []
    for k in kps:
        x0, y0, x1, y1 = clipped_box(float(k.u), float(k.v), float(k.box_size_px), w, h)
        points.append(
            {
                "crossing_id": int(k.crossing_id),
                "u": float(k.u),
                "v": float(k.v),
                "visibility": int(k.visibility),
                "bbox": [x0, y0, x1 - x0, y1 - y0],
                "box_size_px": float(k.box_size_px),
                "depth_m": float(k.depth_m),
                "x_world": float(k.x_world),
                "y_world": float(k.y_world),
                "z_world": float(k.z_world),
                "tie_wire": bool(k.tie_wire),
            }
        )
    row = {name: s[name] for name, _, _ in ROW_FIELDS if name in s}
    row["image"] = {"bytes": image, "path": Path(s["file_name"]).name}
    row["world_from_camera"] = [float(x) for x in np.asarray(s["world_from_camera"], float).reshape(-1)]
    row["keypoints"] = points
    return row


def write_shards(
    dataset: Path, out: Path, samples: pa.Table, keypoints: pa.Table, *, max_bytes: int = SHARD_MAX_BYTES
) -> list[Shard]:
    """Write ``out/data/<split>-NNNNN-of-MMMMM.parquet`` for every non-empty split; rows sorted by image_id."""
    kp = _keypoints_by_image(keypoints)
    rows_of = samples.sort_by("image_id").to_pylist()
    shards: list[Shard] = []
    (out / DATA_DIR).mkdir(parents=True, exist_ok=True)
    for split in layout.SPLITS:
        rows = [s for s in rows_of if s["split"] == split]
        if not rows:
            continue
        groups: list[list[dict]] = [[]]
        size = 0
        for s in rows:
            nbytes = (dataset / s["file_name"]).stat().st_size
            if groups[-1] and size + nbytes > max_bytes:
                groups.append([])
                size = 0
            groups[-1].append(s)
            size += nbytes
        for i, group in enumerate(groups):
            rel = f"{DATA_DIR}/{split}-{i:05d}-of-{len(groups):05d}.parquet"
            table = pa.Table.from_pylist(
                [_row(s, kp.get(s["image_id"], []), (dataset / s["file_name"]).read_bytes()) for s in group],
                schema=ROW_SCHEMA,
            )
            pq.write_table(table, out / rel, compression="zstd", row_group_size=ROW_GROUP_ROWS)
            shards.append(Shard(rel, split, table.num_rows))
    return shards
