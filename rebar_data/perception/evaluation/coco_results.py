"""Detections as COCO keypoint results: the JSON list pycocotools' ``COCO.loadRes`` reads and ``COCOeval``
scores against a dataset's ``annotations/<split>.json``.

One object a detection: ``image_id``, the image's integer id in that file (matched by ``file_name``; the
dataset's string key is not a COCO id), ``category_id``, ``keypoints`` [u, v, 2] in pixels with the corner
origin the annotations use, and ``score``. No ``bbox``: for keypoint results ``loadRes`` computes one from the
keypoints itself, and COCOeval's OKS takes the object's scale from the ground truth's ``area``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from rebar_data.config import ConfigError
from rebar_data.dataset import layout
from rebar_data.dataset.writers.coco import CATEGORY_ID

RESULT_KEYS = ("image_id", "category_id", "keypoints", "score")
VISIBLE = 2  # COCO's "labelled and visible", the flag a detected keypoint carries


def coco_image_ids(root: str | Path, split: str, file_names: Sequence[str]) -> list[int]:
    """The COCO image id of each of ``file_names`` (relative to the dataset folder ``root``, as the samples
    table holds them) in ``annotations/<split>.json``.

    Raises:
        ConfigError: the file is missing or unreadable, or holds no image of one of ``file_names``.
    """
    rel = layout.coco_path(split)
    path = Path(root) / rel
    accepted = f"accepted: the {split} split's COCO keypoints file as `rebar dataset build` writes it"
    try:
        images = json.loads(path.read_text())["images"]
        ids = {str(im["file_name"]): int(im["id"]) for im in images}
    except FileNotFoundError:
        raise ConfigError(f"{path}: missing, so no COCO image ids; {accepted}") from None
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ConfigError(
            f"{path}: has no readable images list ({type(e).__name__}: {e}); {accepted}"
        ) from None
    missing = [f for f in file_names if f not in ids]
    if missing:
        raise ConfigError(
            f"{path}: has no image with file_name {missing[0]!r} ({len(missing)} of the split's "
            f"{len(file_names)} images missing); {accepted}"
        )
    return [ids[f] for f in file_names]


def coco_results(image_ids: Sequence[int], predictions: Sequence[np.ndarray]) -> list[dict]:
    """One result object for each row (u, v, score) of each image's ``predictions``, in their order."""
    out = []
    for image_id, pred in zip(image_ids, predictions, strict=True):
        for u, v, score in np.asarray(pred, float).reshape(-1, 3):
            out.append(
                {
                    "image_id": int(image_id),
                    "category_id": CATEGORY_ID,
                    "keypoints": [float(u), float(v), VISIBLE],
                    "score": float(score),
                }
            )
    return out


def is_coco_results(path: str | Path) -> bool:
    """``path`` holds a list of COCO keypoint results with exactly :data:`RESULT_KEYS` (an empty list too),
    as :func:`coco_results` writes them."""
    try:
        rows = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(rows, list) and all(isinstance(r, dict) and set(r) == set(RESULT_KEYS) for r in rows)
