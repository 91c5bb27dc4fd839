"""Ultralytics YOLO pose labels (``0 cx cy w h px py v``, normalised) and ``data.yaml``.

Only visible keypoints (visibility 2) become YOLO objects: an occluded crossing is not something a
detector should find. Boxes are clipped to the image; the keypoint is never moved. Numbers are written
with Python's shortest round-trip repr, so ``u / width`` read back times ``width`` is ``u``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import yaml

from rebar_data.dataset import layout


def clipped_box(
    u: float, v: float, side: float, width: int, height: int
) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) of the square of ``side`` around (u, v), clipped to the image."""
    h = side / 2.0
    return max(u - h, 0.0), max(v - h, 0.0), min(u + h, float(width)), min(v + h, float(height))


def yolo_lines(kp: dict[str, np.ndarray], width: int, height: int) -> str:
    lines = []
    for u, v, side in zip(kp["u"], kp["v"], kp["box_size_px"], strict=True):
        x0, y0, x1, y1 = clipped_box(float(u), float(v), float(side), width, height)
        vals = [(x0 + x1) / 2 / width, (y0 + y1) / 2 / height, (x1 - x0) / width, (y1 - y0) / height]
        vals += [float(u) / width, float(v) / height]
        lines.append("0 " + " ".join(repr(float(x)) for x in vals) + " 2")
    return "".join(line + "\n" for line in lines)


def write_yolo(out: Path, samples: pa.Table, keypoints: pa.Table) -> None:
    kp = keypoints.filter(pc.equal(keypoints["visibility"], 2)).to_pydict()
    by_image: dict[str, dict[str, list]] = {}
    for i, iid in enumerate(kp["image_id"]):
        d = by_image.setdefault(iid, {"u": [], "v": [], "box_size_px": []})
        for k in d:
            d[k].append(kp[k][i])
    s = samples.to_pydict()
    for iid, split, w, h in zip(s["image_id"], s["split"], s["width"], s["height"], strict=True):
        d = by_image.get(iid, {"u": [], "v": [], "box_size_px": []})
        path = out / layout.label_path(split, iid)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(yolo_lines({k: np.asarray(v, float) for k, v in d.items()}, w, h))


def write_data_yaml(out: Path, *, oks_sigma: float) -> None:
    """Ultralytics' pose dataset file.

    It has no ``path``: Ultralytics then resolves ``train``, ``val`` and ``test`` against the folder of
    ``data.yaml`` itself, so a copied or moved dataset trains from its own images, and its file still matches
    the manifest (a relative ``path`` would be taken under Ultralytics' datasets folder instead; an absolute
    one pins the folder the dataset was built in). ``kpt_oks_sigmas`` carries the dataset's ``oks_sigma``:
    without it Ultralytics scores a single keypoint with sigma 1.0.
    """
    data = {
        "train": "images/train",
        "val": "images/val",
        "test": "images/test",
        "names": {0: layout.CATEGORY},
        "kpt_shape": [1, 3],
        "flip_idx": [0],
        "kpt_oks_sigmas": [float(oks_sigma)],
    }
    (out / layout.DATA_YAML).write_text(yaml.safe_dump(data, sort_keys=False))
