"""COCO keypoints, one file per split (``annotations/<split>.json``).

Like the YOLO labels, annotations are the visible crossings only. ``bbox`` is the keypoint's square box
clipped to the image; ``area`` is the unclipped square's area (``box_size_px ** 2``), which is the
object scale OKS uses. Image and annotation ids are 1-based and unique across the whole dataset.
"""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc

from rebar_data.dataset import layout
from rebar_data.dataset.writers.yolo import clipped_box

CATEGORY_ID = 1


def coco_dicts(samples: pa.Table, keypoints: pa.Table, info: dict) -> dict[str, dict]:
    s = samples.to_pydict()
    image_num = {iid: i + 1 for i, iid in enumerate(s["image_id"])}
    out = {
        split: {
            "info": info,
            "licenses": [],
            "categories": [
                {
                    "id": CATEGORY_ID,
                    "name": layout.CATEGORY,
                    "supercategory": "rebar",
                    "keypoints": list(layout.KEYPOINT_NAMES),
                    "skeleton": [],
                }
            ],
            "images": [],
            "annotations": [],
        }
        for split in layout.SPLITS
    }
    size = {}
    for iid, split, fn, w, h in zip(
        s["image_id"], s["split"], s["file_name"], s["width"], s["height"], strict=True
    ):
        out[split]["images"].append(
            {"id": image_num[iid], "file_name": fn, "width": w, "height": h, "image_key": iid}
        )
        size[iid] = (w, h)
    kp = keypoints.filter(pc.equal(keypoints["visibility"], 2)).to_pydict()
    for ann_id, i in enumerate(range(len(kp["image_id"])), start=1):
        iid = kp["image_id"][i]
        u, v, side = kp["u"][i], kp["v"][i], kp["box_size_px"][i]
        x0, y0, x1, y1 = clipped_box(u, v, side, *size[iid])
        out[kp["split"][i]]["annotations"].append(
            {
                "id": ann_id,
                "image_id": image_num[iid],
                "category_id": CATEGORY_ID,
                "keypoints": [u, v, 2],
                "num_keypoints": 1,
                "bbox": [x0, y0, x1 - x0, y1 - y0],
                "area": side * side,
                "iscrowd": 0,
                "crossing_id": kp["crossing_id"][i],
            }
        )
    return out


def write_coco(out: Path, samples: pa.Table, keypoints: pa.Table, info: dict) -> None:
    (out / "annotations").mkdir(parents=True, exist_ok=True)
    for split, d in coco_dicts(samples, keypoints, info).items():
        (out / layout.coco_path(split)).write_text(json.dumps(d, sort_keys=True, separators=(",", ":")))
