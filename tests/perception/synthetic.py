"""A drawn stand-in for a rendered dataset: perspective rebar grids painted with OpenCV, in the dataset layout.

The detector, its training loop and its metrics are tested against the dataset contract, not against the
renderer: this module draws a grid of rusty bars on a textured ground, seen by a pinhole camera along short
trajectories, and writes the images with exact crossing positions in the contract's layout (``meta/``,
``images/``, ``tables/``, ``annotations/``, ``labels/``). A plank laid over part of some frames hides
crossings, which are then marked occluded (visibility 1). It takes a fraction of a second per frame, so
tests can build a dataset in ``tmp_path``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

SPLITS = ("train", "val", "test")
_SHIFT = 4  # fixed-point bits for OpenCV's sub-pixel drawing
_SCALE = 1 << _SHIFT


@dataclass(frozen=True)
class SyntheticSpec:
    """What to draw: image size, camera, grid and how many trajectories of how many frames.

    Attributes:
        width: Image width in pixels.
        height: Image height in pixels.
        focal_px: Focal length in pixels (fx = fy); the principal point is the image centre.
        trajectories: Camera trajectories; whole trajectories go to one split.
        frames: Frames per trajectory.
        standoff_m: Camera height above the mat, (min, max).
        tilt_rad: Largest angle between the optical axis and the mat's normal.
        spacing_m: Bar spacing in both directions.
        bar_diameter_m: Bar diameter.
        bars: Bars per direction.
        occluder_fraction: Share of frames with a plank laid over the mat.
        shadow_fraction: Share of frames where the mat casts a sharp shadow on the ground below it, a grid
            of dark crossings that are not crossings.
        splits: Share of trajectories for train, val, test (at least one each when there are three or more).
    """

    width: int = 320
    height: int = 240
    focal_px: float = 262.5
    trajectories: int = 6
    frames: int = 3
    standoff_m: tuple[float, float] = (0.55, 0.9)
    tilt_rad: float = 0.5
    spacing_m: float = 0.1
    bar_diameter_m: float = 0.012
    bars: int = 16
    occluder_fraction: float = 0.5
    shadow_fraction: float = 0.5
    splits: tuple[float, float, float] = (0.7, 0.15, 0.15)


def write_synthetic_dataset(
    root: str | Path, spec: SyntheticSpec | None = None, *, seed: int = 0, name: str = "drawn"
) -> Path:
    """Draw a dataset and write it in the contract layout under ``root/<name>/v0.0.0/``.

    Args:
        root: Folder to write under (created if missing).
        spec: What to draw; the defaults give 18 frames of 320x240.
        seed: Seed of the one generator every draw comes from.
        name: Dataset name.

    Returns:
        The dataset folder.
    """
    spec = spec or SyntheticSpec()
    rng = np.random.default_rng(seed)
    out = Path(root) / name / "v0.0.0"
    for sub in (
        "meta",
        "tables",
        "annotations",
        *(f"images/{s}" for s in SPLITS),
        *(f"labels/{s}" for s in SPLITS),
        *(f"depth/{s}" for s in SPLITS),
    ):
        (out / sub).mkdir(parents=True, exist_ok=True)
    split_of_traj = _assign_splits(spec.trajectories, spec.splits, rng)
    crossings_world = grid_crossings(spec)
    samples: list[dict] = []
    keypoints: list[dict] = []
    for t in range(spec.trajectories):
        poses = random_trajectory(spec, rng)
        for f, world_from_camera in enumerate(poses):
            image_id = f"t{t:03d}_f{f:03d}"
            split = split_of_traj[t]
            rgb, kps, depth_m = draw_frame(spec, world_from_camera, crossings_world, rng)
            file_name = f"images/{split}/{image_id}.png"
            cv2.imwrite(str(out / file_name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            depth_mm = np.clip(np.rint(depth_m * 1000.0), 0, 65535).astype(np.uint16)
            cv2.imwrite(str(out / f"depth/{split}/{image_id}.png"), depth_mm)
            samples.append(
                {
                    "image_id": image_id,
                    "split": split,
                    "file_name": file_name,
                    "width": spec.width,
                    "height": spec.height,
                    "fx": spec.focal_px,
                    "fy": spec.focal_px,
                    "cx": spec.width / 2,
                    "cy": spec.height / 2,
                    "world_from_camera": world_from_camera.reshape(-1).tolist(),
                    "scene_id": 0,
                    "trajectory_id": t,
                }
            )
            for k in kps:
                keypoints.append({"image_id": image_id, "split": split, **k})
    _write_tables(out, samples, keypoints)
    _write_coco_and_yolo(out, samples, keypoints)
    counts = {s: sum(r["split"] == s for r in samples) for s in SPLITS}
    info = {
        "name": name,
        "version": "0.0.0",
        "schema_version": 1,
        "generator": "tests.perception.synthetic",
        "seed": seed,
        "image_size": {"width": spec.width, "height": spec.height},
        "keypoint_names": ["intersection"],
        "split": {"rule": "trajectory", "fractions": list(spec.splits)},
        "counts": {"images": counts, "keypoints": len(keypoints)},
    }
    (out / "meta/info.json").write_text(json.dumps(info, indent=2, sort_keys=True) + "\n")
    return out


def _assign_splits(n: int, fractions: tuple[float, float, float], rng: np.random.Generator) -> list[str]:
    order = rng.permutation(n)
    n_val = max(1, round(fractions[1] * n)) if n >= 3 else 0
    n_test = max(1, round(fractions[2] * n)) if n >= 3 else 0
    split = ["train"] * n
    for i in order[:n_val]:
        split[i] = "val"
    for i in order[n_val : n_val + n_test]:
        split[i] = "test"
    return split


def grid_crossings(spec: SyntheticSpec) -> np.ndarray:
    """World points of every crossing: the midpoint between the two touching centrelines."""
    pos = (np.arange(spec.bars) - (spec.bars - 1) / 2) * spec.spacing_m
    xx, yy = np.meshgrid(pos, pos, indexing="ij")
    z = np.full(xx.size, spec.bar_diameter_m)  # lower bars' axis at d/2, upper bars' at 3d/2
    return np.c_[xx.ravel(), yy.ravel(), z]


def _look_at(eye: np.ndarray, target: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """world_from_camera for an OpenCV camera at ``eye`` looking at ``target`` with a random roll."""
    z = target - eye
    z /= np.linalg.norm(z)
    roll = rng.uniform(-np.pi, np.pi)
    up = np.array([np.cos(roll), np.sin(roll), 0.0])
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    t = np.eye(4)
    t[:3, :3] = np.c_[x, y, z]
    t[:3, 3] = eye
    return t


def random_trajectory(spec: SyntheticSpec, rng: np.random.Generator) -> list[np.ndarray]:
    """A straight pass over the mat: the camera and its look-at point move a little each frame."""
    half = spec.spacing_m * (spec.bars - 1) / 2
    target = np.r_[rng.uniform(-0.3, 0.3, 2) * half, 0.0]
    step = np.r_[rng.normal(0, 0.03, 2), 0.0]
    height = rng.uniform(*spec.standoff_m)
    tilt = rng.uniform(0, spec.tilt_rad)
    azimuth = rng.uniform(-np.pi, np.pi)
    offset = height * np.tan(tilt) * np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
    poses = []
    for f in range(spec.frames):
        tgt = target + f * step
        eye = tgt + offset + np.array([0.0, 0.0, height])
        poses.append(_look_at(eye, tgt, rng))
    return poses


def _project(points_world: np.ndarray, world_from_camera: np.ndarray, f: float, cx: float, cy: float):
    camera_from_world = np.linalg.inv(world_from_camera)
    pc = points_world @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.c_[f * pc[:, 0] / z + cx, f * pc[:, 1] / z + cy]
    return uv, z


def _texture(h: int, w: int, rng: np.random.Generator, *, base: np.ndarray, contrast: float) -> np.ndarray:
    """Multi-scale value noise around a base colour: concrete, soil or rust."""
    acc = np.zeros((h, w), np.float32)
    for cells, amp in ((4, 1.0), (16, 0.5), (64, 0.3), (max(h, w) // 2, 0.25)):
        small = rng.standard_normal((max(2, cells * h // max(h, w)), cells)).astype(np.float32)
        acc += amp * cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    acc /= acc.std() + 1e-6
    tint = 1.0 + rng.normal(0, 0.08, 3)
    img = base[None, None, :] * tint * (1.0 + contrast * acc[..., None])
    return np.clip(img, 0, 255).astype(np.float32)


def _draw_bar(
    canvas: np.ndarray,
    start: np.ndarray,
    end: np.ndarray,
    across: np.ndarray,
    *,
    diameter_m: float,
    colour: np.ndarray,
    light: float,
    cam: tuple[np.ndarray, float, float, float],
    shaded: bool = True,
) -> None:
    """Paint one bar as short shaded ribbons (bright along its lit side), in perspective."""
    world_from_camera, f, cx, cy = cam
    n_seg = 24
    strips = 5
    ts = np.linspace(0, 1, n_seg + 1)
    axis = start[None, :] + ts[:, None] * (end - start)[None, :]
    for s in range(strips):
        a0, a1 = -0.5 + s / strips, -0.5 + (s + 1) / strips
        angle = (a0 + a1) / 2 * np.pi
        shade = 0.35 + 0.75 * max(0.0, np.cos(angle - light)) if shaded else 1.0
        c = np.clip(colour * shade, 0, 255)
        left = axis + a0 * diameter_m * across
        right = axis + a1 * diameter_m * across
        uv_l, z_l = _project(left, world_from_camera, f, cx, cy)
        uv_r, z_r = _project(right, world_from_camera, f, cx, cy)
        for i in range(n_seg):
            if min(z_l[i], z_l[i + 1], z_r[i], z_r[i + 1]) < 0.05:
                continue
            quad = np.array([uv_l[i], uv_l[i + 1], uv_r[i + 1], uv_r[i]])
            pts = np.round((quad - 0.5) * _SCALE).astype(np.int32)  # COCO corner origin -> pixel index
            cv2.fillConvexPoly(canvas, pts, c.tolist(), lineType=cv2.LINE_AA, shift=_SHIFT)


def draw_frame(
    spec: SyntheticSpec,
    world_from_camera: np.ndarray,
    crossings_world: np.ndarray,
    rng: np.random.Generator,
) -> tuple[np.ndarray, list[dict], np.ndarray]:
    """Draw one frame; return the RGB image, one keypoint record per crossing and the depth image.

    Keypoints follow the contract: COCO corner origin, visibility 0 outside the image, 1 under the plank,
    2 visible, and a square box of four bar diameters (``box_size_px``). The depth image (float32 metres
    of camera-frame z) is flat per surface: the ground, each bar direction's top at its height, the plank
    above them; enough for the depth check to tell bars that lie on each other.
    """
    h, w, f = spec.height, spec.width, spec.focal_px
    cx, cy = w / 2, h / 2
    cam = (world_from_camera, f, cx, cy)
    ground = np.array([rng.uniform(90, 170)] * 3) * (1 + rng.normal(0, 0.1, 3))
    img = _texture(h, w, rng, base=ground, contrast=rng.uniform(0.08, 0.25))
    rust = np.array([rng.uniform(110, 170), rng.uniform(55, 95), rng.uniform(25, 55)])
    half = spec.spacing_m * (spec.bars - 1) / 2
    ext = half + spec.spacing_m * 0.7
    pos = (np.arange(spec.bars) - (spec.bars - 1) / 2) * spec.spacing_m
    d = spec.bar_diameter_m
    light = rng.uniform(-0.8, 0.8)
    if rng.uniform() < spec.shadow_fraction:
        _draw_shadow(img, spec, pos, ext, rng, cam=cam)
    # direction-1 bars (along y) lie beneath, direction-0 bars (along x) on top of them; bars of one
    # direction never overlap, so each direction is painted on its own layer and laid over the ground
    depth_img = _plane_depth(0.0, spec, world_from_camera)
    for y_dir, z_axis in ((1, d / 2), (0, 1.5 * d)):
        layer = np.zeros((h, w, 3), np.float32)
        for p in pos:
            colour = rust * (1 + rng.normal(0, 0.12, 3))
            if y_dir:
                start, end, across = (
                    np.array([p, -ext, z_axis]),
                    np.array([p, ext, z_axis]),
                    np.array([1.0, 0, 0]),
                )
            else:
                start, end, across = (
                    np.array([-ext, p, z_axis]),
                    np.array([ext, p, z_axis]),
                    np.array([0, 1.0, 0]),
                )
            jitter = rng.normal(0, 0.0005, 3) * [1, 1, 0]
            _draw_bar(
                layer, start + jitter, end + jitter, across, diameter_m=d, colour=colour, light=light, cam=cam
            )
        mask = layer.max(axis=2) > 0
        img[mask] = layer[mask]
        depth_img[mask] = _plane_depth(z_axis + d / 2, spec, world_from_camera)[mask]
    midpoints = crossings_world  # the 3D crossing points, as the dataset's x_crossing, y_crossing, z_crossing
    crossings_world = _sight_points(crossings_world, d, world_from_camera[:3, 3])
    uv, z = _project(crossings_world, world_from_camera, f, cx, cy)
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    occluded = np.zeros(len(uv), bool)
    if rng.uniform() < spec.occluder_fraction:
        plank = _plank(h, w, rng)
        cv2.fillConvexPoly(img, plank, (rng.uniform(60, 200),) * 3, lineType=cv2.LINE_AA)
        covered = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(covered, plank, 1)
        depth_img[covered > 0] = _plane_depth(4 * d, spec, world_from_camera)[covered > 0]
        for i in np.flatnonzero(inside):
            occluded[i] = cv2.pointPolygonTest(plank.astype(np.float32), tuple(uv[i] - 0.5), True) > -1.0
    img = _sensor(img, rng)
    records = []
    for i, (pw, (u, v), depth) in enumerate(zip(crossings_world, uv, z, strict=True)):
        if depth <= 0:
            continue
        vis = 0 if not inside[i] else (1 if occluded[i] else 2)
        records.append(
            {
                "u": float(u),
                "v": float(v),
                "visibility": vis,
                "x_world": float(pw[0]),
                "y_world": float(pw[1]),
                "z_world": float(pw[2]),
                "depth_m": float(depth),
                "box_size_px": float(4 * d * f / depth),
                "crossing_id": i,
                "x_crossing": float(midpoints[i, 0]),
                "y_crossing": float(midpoints[i, 1]),
                "z_crossing": float(midpoints[i, 2]),
            }
        )
    return img, records, depth_img


def _plane_depth(height_m: float, spec: SyntheticSpec, world_from_camera: np.ndarray) -> np.ndarray:
    """(H, W) float32 camera-frame z at which each pixel centre's ray meets the plane z_world = height_m
    (0 where it does not, in front of the camera)."""
    h, w, f = spec.height, spec.width, spec.focal_px
    u, v = np.meshgrid((np.arange(w) + 0.5 - w / 2) / f, (np.arange(h) + 0.5 - h / 2) / f)
    R, C = world_from_camera[:3, :3], world_from_camera[:3, 3]
    rise = R[2, 0] * u + R[2, 1] * v + R[2, 2]  # world z of each ray direction (camera z = 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (height_m - C[2]) / rise
    return np.where(np.isfinite(z) & (z > 0), z, 0.0).astype(np.float32)


def _sight_points(crossings_world: np.ndarray, d: float, camera_centre: np.ndarray) -> np.ndarray:
    """Where each crossing is seen, as the dataset labels it: the sight point of the top bar's axis
    (along x, d/2 above the crossing) and the bottom bar's (along y, d/2 below)."""
    from rebar_data.labels.keypoints import sight_points_on_lines

    n = len(crossings_world)
    q, _ = sight_points_on_lines(
        crossings_world + [0.0, 0.0, d / 2],
        np.tile([1.0, 0.0, 0.0], (n, 1)),
        crossings_world - [0.0, 0.0, d / 2],
        np.tile([0.0, 1.0, 0.0], (n, 1)),
        camera_centre,
    )
    return q


def _draw_shadow(
    img: np.ndarray,
    spec: SyntheticSpec,
    pos: np.ndarray,
    ext: float,
    rng: np.random.Generator,
    *,
    cam: tuple[np.ndarray, float, float, float],
) -> None:
    """Darken the ground where the bars' shadow falls, for a distant light, on a ground plane below the mat."""
    ground_z = -rng.uniform(0.05, 0.3)
    slope = rng.uniform(-0.8, 0.8, 2)  # horizontal shift of the shadow per metre of height
    mask = np.zeros(img.shape, np.float32)
    white = np.array([1.0, 1.0, 1.0])
    for y_dir, z_axis in ((1, spec.bar_diameter_m / 2), (0, 1.5 * spec.bar_diameter_m)):
        shift = np.r_[slope * (z_axis - ground_z), ground_z - z_axis]
        for p in pos:
            if y_dir:
                start, end, across = (
                    np.array([p, -ext, z_axis]),
                    np.array([p, ext, z_axis]),
                    np.array([1.0, 0, 0]),
                )
            else:
                start, end, across = (
                    np.array([-ext, p, z_axis]),
                    np.array([ext, p, z_axis]),
                    np.array([0, 1.0, 0]),
                )
            _draw_bar(
                mask,
                start + shift,
                end + shift,
                across,
                diameter_m=spec.bar_diameter_m,
                colour=white,
                light=0.0,
                cam=cam,
                shaded=False,
            )
    img *= 1.0 - rng.uniform(0.35, 0.65) * np.clip(mask, 0, 1)


def random_frame(spec: SyntheticSpec, rng: np.random.Generator) -> tuple[np.ndarray, list[dict], np.ndarray]:
    """One frame from a random camera pose: the RGB image, its keypoint records and its depth image."""
    return draw_frame(spec, random_trajectory(spec, rng)[0], grid_crossings(spec), rng)


def _plank(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    c = np.array([rng.uniform(0.2, 0.8) * w, rng.uniform(0.2, 0.8) * h])
    angle = rng.uniform(0, np.pi)
    along = np.array([np.cos(angle), np.sin(angle)]) * max(h, w)
    across = np.array([-np.sin(angle), np.cos(angle)]) * rng.uniform(0.05, 0.15) * min(h, w)
    return np.round(
        np.array([c - along - across, c + along - across, c + along + across, c - along + across])
    ).astype(np.int32)


def _sensor(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    img = img * rng.uniform(0.7, 1.2)
    img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.3, 0.8))
    img = img + rng.normal(0, rng.uniform(1, 5), img.shape).astype(np.float32)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def _write_tables(out: Path, samples: list[dict], keypoints: list[dict]) -> None:
    s_schema = pa.schema(
        [
            ("image_id", pa.string()),
            ("split", pa.string()),
            ("file_name", pa.string()),
            ("width", pa.int32()),
            ("height", pa.int32()),
            ("fx", pa.float64()),
            ("fy", pa.float64()),
            ("cx", pa.float64()),
            ("cy", pa.float64()),
            ("world_from_camera", pa.list_(pa.float64(), 16)),
            ("scene_id", pa.int32()),
            ("trajectory_id", pa.int32()),
        ]
    )
    pq.write_table(pa.Table.from_pylist(samples, schema=s_schema), out / "tables/samples.parquet")
    k_schema = pa.schema(
        [
            ("image_id", pa.string()),
            ("split", pa.string()),
            ("u", pa.float64()),
            ("v", pa.float64()),
            ("visibility", pa.int8()),
            ("x_world", pa.float64()),
            ("y_world", pa.float64()),
            ("z_world", pa.float64()),
            ("depth_m", pa.float64()),
            ("box_size_px", pa.float64()),
            ("crossing_id", pa.int32()),
            ("x_crossing", pa.float64()),
            ("y_crossing", pa.float64()),
            ("z_crossing", pa.float64()),
        ]
    )
    pq.write_table(pa.Table.from_pylist(keypoints, schema=k_schema), out / "tables/keypoints.parquet")


def _write_coco_and_yolo(out: Path, samples: list[dict], keypoints: list[dict]) -> None:
    by_image: dict[str, list[dict]] = {}
    for k in keypoints:
        if k["visibility"] > 0:
            by_image.setdefault(k["image_id"], []).append(k)
    for split in SPLITS:
        images, anns = [], []
        for num, s in enumerate(r for r in samples if r["split"] == split):
            images.append(
                {"id": num + 1, "file_name": s["file_name"], "width": s["width"], "height": s["height"]}
            )
            lines = []
            for k in by_image.get(s["image_id"], []):
                b = k["box_size_px"]
                anns.append(
                    {
                        "id": len(anns) + 1,
                        "image_id": num + 1,
                        "category_id": 1,
                        "bbox": [k["u"] - b / 2, k["v"] - b / 2, b, b],
                        "area": b * b,
                        "iscrowd": 0,
                        "num_keypoints": 1,
                        "keypoints": [k["u"], k["v"], k["visibility"]],
                    }
                )
                w, h = s["width"], s["height"]
                lines.append(
                    f"0 {k['u'] / w:.6f} {k['v'] / h:.6f} {b / w:.6f} {b / h:.6f} "
                    f"{k['u'] / w:.6f} {k['v'] / h:.6f} {k['visibility']}"
                )
            (out / "labels" / split / f"{s['image_id']}.txt").write_text("".join(x + "\n" for x in lines))
        coco = {
            "images": images,
            "annotations": anns,
            "categories": [{"id": 1, "name": "intersection", "keypoints": ["intersection"], "skeleton": []}],
        }
        (out / "annotations" / f"{split}.json").write_text(json.dumps(coco))


def drawn_frame_labelled() -> tuple[np.ndarray, list[dict], np.ndarray]:
    """A drawn 640x480 rebar frame dense with bars (focal length 525 px), its keypoint records and depth."""
    spec = SyntheticSpec(width=640, height=480, focal_px=525.0, occluder_fraction=0.0)
    return random_frame(spec, np.random.default_rng(0))


def drawn_frame() -> tuple[np.ndarray, np.ndarray]:
    """:func:`drawn_frame_labelled`'s image and depth."""
    rgb, _, depth = drawn_frame_labelled()
    return rgb, depth
