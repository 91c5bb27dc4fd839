"""The dataset card, ``README.md`` in the dataset folder, and the parts a release bundle's card shares.

The card says what the dataset is (name, version, counts per split, image size, intrinsics, the keypoint,
its visibility and OKS conventions), how the folder is laid out, and how to score detections on it with
pycocotools. pycocotools' keypoint defaults are COCO's people: 17 sigmas (an IndexError on one keypoint)
and 20 detections an image (our images hold more crossings), so the card gives a snippet with both set.
Everything comes from ``meta/info.json`` and the keypoints table, so the card is the same whatever the
number of workers; the manifest lists it like any other file.
"""

from __future__ import annotations

from pathlib import Path

import pyarrow.compute as pc
import pyarrow.parquet as pq

from rebar_data.dataset import layout
from rebar_data.dataset.layout import DatasetInfo

CARD = "README.md"
PREDICTIONS = "predictions.json"
PIP_PYCOCOTOOLS = "pip install pycocotools"  # the first line of the COCOeval snippet: all it needs


def max_dets(max_visible: int | None) -> int:
    """COCOeval's ``maxDets`` for images with up to ``max_visible`` visible crossings: a multiple of 100
    that counts every one of them (1000 when the number is unknown)."""
    if max_visible is None:
        return 1000
    return max(100, -(-int(max_visible) // 100) * 100)


def max_visible_per_image(dataset: Path) -> int:
    """The most visible crossings (visibility 2) in one image of the dataset at ``dataset``."""
    k = pq.read_table(Path(dataset) / layout.KEYPOINTS, columns=["image_id", "visibility"])
    visible = k.filter(pc.equal(k["visibility"], 2))
    if visible.num_rows == 0:
        return 0
    per_image = visible.group_by("image_id").aggregate([("visibility", "count")])["visibility_count"]
    return int(pc.max(per_image).as_py())


def cocoeval_snippet(oks_sigma: float, *, max_visible: int | None, split: str = "val") -> str:
    """Python that scores the COCO keypoint results ``RESULTS`` against ``annotations/<split>.json`` of the
    dataset folder ``DATASET`` with COCOeval; it prints and leaves ``ap`` (OKS 0.50:0.95) and ``ap50`` (OKS
    0.5). It needs pycocotools alone (numpy comes with it), as its first line says."""
    n = max_dets(max_visible)
    most = f"up to {max_visible}" if max_visible is not None else "many"
    return "\n".join(
        [
            f"# {PIP_PYCOCOTOOLS}",
            "import numpy as np",
            "from pycocotools.coco import COCO",
            "from pycocotools.cocoeval import COCOeval",
            "",
            'DATASET = "."  # this folder',
            f'RESULTS = "{PREDICTIONS}"  # `rebar score DATASET --split {split} --coco-results {PREDICTIONS}`',
            f'gt = COCO(f"{{DATASET}}/annotations/{split}.json")',
            f'dt = gt.loadRes(RESULTS)  # [{{"image_id": its id in {split}.json, "category_id": 1, "keypoints": [u, v, 2], "score"}}]',
            'E = COCOeval(gt, dt, iouType="keypoints")',
            f"E.params.kpt_oks_sigmas = np.array([{oks_sigma!r}])  # one keypoint; COCO's 17 sigmas raise IndexError",
            f"E.params.maxDets = [{n}]  # {most} visible crossings an image; the default 20 drops the rest",
            "E.evaluate()",
            "E.accumulate()",
            '# precision[OKS threshold, recall point]; category 1, area "all", maxDets[0]. E.summarize() would',
            "# print -1 here: its keypoint summary reads maxDets 20 only.",
            'p = E.eval["precision"][:, :, 0, 0, 0]',
            "ap, ap50 = p[p > -1].mean(), p[0][p[0] > -1].mean()",
            'print(f"AP {ap:.3f} (OKS 0.50:0.95), AP@0.5 {ap50:.3f}")',
        ]
    )


def cocoeval_lines(info: DatasetInfo, *, max_visible: int | None, heading: str = "##") -> list[str]:
    """The card section that says how to score detections with pycocotools."""
    return [
        f"{heading} Score detections with pycocotools",
        "",
        "Write your detections as COCO keypoint results (u, v in pixels with the labels' corner origin; one "
        "object per detected crossing; `image_id` the image's integer id in `annotations/<split>.json`), or "
        f"let `rebar score DATASET --split val --coco-results {PREDICTIONS}` write them, set `DATASET` to "
        "this folder and `RESULTS` to that file, and run this (`annotations/test.json` for the test split). It "
        f"scores with this dataset's sigma, {info.oks_sigma}, and counts every detection of an image:",
        "",
        "```python",
        cocoeval_snippet(info.oks_sigma, max_visible=max_visible),
        "```",
    ]


def label_lines(info: DatasetInfo) -> list[str]:
    """What the labels mean: keypoint, pixels, camera, visibility, boxes and OKS (a Markdown list)."""
    k = info.intrinsics
    sigma = info.oks_sigma
    return [
        f"- One keypoint class, `{', '.join(info.keypoint_names)}` (COCO category `{layout.CATEGORY}`): the "
        "pixel where the image shows two bars cross, where their projected centerlines meet on the nearer "
        "bar's centerline. The crossing's 3D point (inside the steel) is kept beside it in the tables.",
        f"- Pixels: {k.get('convention')}; fx {k['fx']}, fy {k['fy']}, cx {k['cx']}, cy {k['cy']}. "
        "The pixel origin is the top-left corner of the top-left pixel (COCO).",
        f"- Camera: {info.conventions.get('camera')}; `world_from_camera` maps camera points into the world "
        "(row-major 4x4, metres).",
        f"- Visibility: {info.conventions.get('visibility')}. Visible means the first surface a ray from the "
        "camera meets is one of the crossing's own bars or its tie wire, near the crossing.",
        "- Boxes: a square of four projected bar diameters (at least 8 px) centred on the keypoint; `bbox` is "
        "that square clipped to the image (COCO x, y, w, h), `box_size_px` the unclipped side.",
        f"- YOLO and COCO objects: {info.conventions.get('yolo_coco_objects')}; the tables keep the occluded "
        "ones (visibility 1) and those outside the image (0) too.",
        f"- OKS: sigma {sigma} with area {info.oks_area}; with COCO's OKS = exp(-d^2 / (2 s^2 (2 sigma)^2)), "
        f"OKS 0.5 is an error of {2.355 * sigma:.3g} box sizes ({2.355 * sigma * 25:.2g} px for a 25 px box). "
        f"`data.yaml` gives Ultralytics the same sigma (`kpt_oks_sigmas: [{sigma}]`); Ultralytics takes 0.53 "
        "times the clipped box's area for s^2, so its OKS is somewhat stricter than this one.",
    ]


def _table(rows: list[list], head: list[str]) -> list[str]:
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return out + ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]


def dataset_card(info: DatasetInfo, *, max_visible: int | None, maps: tuple[str, ...] = ()) -> str:
    """The whole card of a dataset folder; ``maps`` names the map folders it holds (depth, instances)."""
    c = info.counts
    size = info.image_size
    gen = info.generator
    n_images = sum(c[s]["images"] for s in layout.SPLITS)
    n_visible = sum(c[s]["visible"] for s in layout.SPLITS)
    lines = [
        f"# {info.name} v{info.version}",
        "",
        *([info.description.strip(), ""] if info.description.strip() else []),
        f"{n_images} synthetic {size['width']}x{size['height']} RGB images of rebar with {n_visible} visible "
        "bar crossings, each labelled with an exact keypoint, a visibility flag, a box and its 3D point, "
        "computed from the geometry and the camera rather than drawn by annotators. Written by "
        f"`rebar dataset build` ({gen.get('name')} {gen.get('version')}, commit `{gen.get('git_commit')}`) "
        f"from a config with sha256 `{info.config_hash}` and seed {info.seed}; dataset schema "
        f"{info.schema_version}. `meta/info.json` holds the whole record.",
        "",
        "## Contents",
        "",
        f"Split rule **{info.split.get('rule')}**; every crossing of the mesh has a row per image in "
        "`tables/keypoints.parquet`, also when it is outside the image.",
        "",
    ]
    lines += _table(
        [
            [f"`{s}`", c[s]["images"], c[s]["keypoints"], c[s]["visible"], c[s]["occluded"], c[s]["outside"]]
            for s in layout.SPLITS
        ],
        ["split", "images", "keypoint rows", "visible (2)", "occluded (1)", "outside (0)"],
    )
    k = info.intrinsics
    lines += [
        "",
        f"Images {size['width']}x{size['height']} px; intrinsics fx {k['fx']}, fy {k['fy']}, cx {k['cx']}, "
        f"cy {k['cy']} px; up to {max_visible} visible crossings in one image.",
        "",
        "## Labels",
        "",
        *label_lines(info),
        "",
        "## Layout",
        "",
        "```",
        "README.md                        this card",
        "meta/info.json                   provenance, resolved config, counts, conventions, oks_sigma",
        "meta/manifest.parquet            path, bytes and sha256 of every other file (audit/ excepted)",
        "data.yaml                        Ultralytics pose dataset (kpt_shape [1, 3], flip_idx [0], kpt_oks_sigmas)",
        "images/<split>/<image_id>.png    RGB",
    ]
    if "depth" in maps:
        lines.append("depth/<split>/<image_id>.png     uint16 millimetres of camera-frame z (0 = nothing)")
    if "instances" in maps:
        lines.append(
            "instances/<split>/<image_id>.png uint16 instance id + 3 (0 distractor, 1 ground, 2 none)"
        )
    lines += [
        "labels/<split>/<image_id>.txt    YOLO pose: `0 cx cy w h px py v`, normalised to [0, 1]",
        "annotations/<split>.json         COCO keypoints",
        "tables/samples.parquet           one row per image: camera, trajectory, scene, every randomized parameter",
        "tables/keypoints.parquet         one row per crossing per image",
        "audit/                           written by `rebar dataset audit`",
        "```",
        "",
        "`rebar dataset validate FOLDER` checks every file against the contract and the manifest.",
        "",
        "## Use it",
        "",
        "- Ultralytics YOLO pose: `YOLO('yolo11n-pose.yaml').train(data=str(Path('data.yaml').resolve()))`. "
        "`data.yaml` has no `path`, so Ultralytics takes the folder of `data.yaml` as the dataset's, wherever "
        "it is copied or moved; nothing needs editing (an edit would fail `rebar dataset validate`).",
        "- Tables: `pandas.read_parquet('tables/keypoints.parquet')` and `tables/samples.parquet`.",
        "",
        *cocoeval_lines(info, max_visible=max_visible),
        "",
    ]
    return "\n".join(lines)


def write_card(out: Path, info: DatasetInfo) -> None:
    """Write ``README.md`` into the dataset folder ``out`` (its tables written already)."""
    out = Path(out)
    maps = tuple(d for d in ("depth", "instances") if (out / d).is_dir())
    text = dataset_card(info, max_visible=max_visible_per_image(out), maps=maps)
    (out / CARD).write_text(text)
