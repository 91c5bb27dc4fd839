"""Where a lower bar mat shows crossing-like places in a dataset's images: negatives the labels imply.

A scene with a lower mat (``surr_lower_layer``) draws the top mat's bars again deeper and shifted
(:mod:`rebar_data.scene.surroundings`). Its own crossings, and the places where a top bar passes in front of
a lower bar, look like the top mat's crossings. Their places are found from the bars rebuilt from
``meta/info.json``, moved as the scene moved them and crossed as each camera sees them; one counts where the
depth image (within ``DEPTH_TOLERANCE_M``) and the instance map (within ``REACH_PX``) confirm it, or, with
neither image, wherever it lies inside the frame."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from rebar_data.camera import Projection, project
from rebar_data.config import ConfigError, validate
from rebar_data.dataset.layout import mesh_sections
from rebar_data.geometry.build import build_rebar_mesh
from rebar_data.geometry.config import MeshConfig
from rebar_data.geometry.crossings import find_crossings
from rebar_data.geometry.curves import sample
from rebar_data.geometry.specs import build_layout
from rebar_data.perception.evaluation.data import Sample, read_distractors, read_info, read_uint16
from rebar_data.scene.mat_surface import MatSurface

# a crossing shows where the depth is this close to the nearer bar's centreline (its surface: within 10 mm)
DEPTH_TOLERANCE_M = 0.02
REACH_PX = 2.0  # the lower mat shows within this many pixels, beyond the widest top bar's half-width (10 mm)
# a top bar in front of a lower bar of the other direction, and the lower mat's own crossings
KINDS = ("top_over_lower", "own")
CHORD_M = 0.05  # the bars are cut into chords this long (a bowed or curved bar's chord errs by under 1 mm)
_COLUMNS = ("surr_lower_layer", *(f"surr_lower_layer_{c}" for c in ("depth_m", "shift_a_m", "shift_b_m")))


@dataclass(frozen=True)
class _Chords:
    """The top mat's bars as chords: (N, 2, 3) world end points, surface coordinates and heights of the
    ends, and each chord's bar direction (0 or 1)."""

    surf: MatSurface
    ends: np.ndarray
    ab: np.ndarray
    height: np.ndarray
    direction: np.ndarray

    def lowered(self, shift: np.ndarray, depth_m: float) -> np.ndarray:
        """The chords' end points in the lower mat."""
        moved = self.surf.frame(self.ab.reshape(-1, 2) + shift, self.height.reshape(-1) - depth_m)[0]
        return moved.reshape(self.ends.shape)


def lower_mat_crossings(root: str | Path, samples: list[Sample]) -> list[np.ndarray]:
    """(M, 2) u, v (COCO corner origin) of the crossings each sample's lower mat shows (its own, and those of
    top bars with lower bars); empty without a lower mat, as for every sample of a dataset recording none."""
    return [np.concatenate([k[name] for name in KINDS]) for k in lower_mat_places(root, samples)]


def lower_mat_places(root: str | Path, samples: list[Sample]) -> list[dict[str, np.ndarray]]:
    """:func:`lower_mat_crossings` by kind: for each sample, ``KINDS`` -> (M, 2) u, v."""
    root = Path(root)
    table = pq.read_table(root / "tables/samples.parquet")
    empty = [{name: np.zeros((0, 2)) for name in KINDS} for _ in samples]
    if not all(c in table.column_names for c in _COLUMNS) or not samples:
        return empty
    cols = table.select(["image_id", "world_from_camera", *_COLUMNS]).to_pydict()
    row = {iid: i for i, iid in enumerate(cols["image_id"])}
    if not any(cols["surr_lower_layer"][row[s.image_id]] for s in samples if s.image_id in row):
        return empty
    top = _chords(root)
    out = []
    for s, none in zip(samples, empty, strict=True):
        i = row.get(s.image_id)
        if i is None or not cols["surr_lower_layer"][i] or s.camera is None:
            out.append(none)
            continue
        shift = np.array([cols["surr_lower_layer_shift_a_m"][i], cols["surr_lower_layer_shift_b_m"][i]])
        low = top.lowered(shift, cols["surr_lower_layer_depth_m"][i])
        world_from_camera = np.asarray(cols["world_from_camera"][i], float).reshape(4, 4)
        cam = _Camera(world_from_camera, s)
        t0, t1 = cam.visible(top.ends[top.direction == 0]), cam.visible(top.ends[top.direction == 1])
        l0, l1 = cam.visible(low[top.direction == 0]), cam.visible(low[top.direction == 1])
        found = [cam.cross(a, b) for a, b in ((t0, l1), (l0, t1), (l0, l1))]  # KINDS' order
        uv = np.concatenate([f[0] for f in found])
        seen = _seen(s, uv, np.concatenate([f[1] for f in found])) if len(uv) else np.zeros(0, bool)
        n = len(found[0][0]) + len(found[1][0])  # the top bars in front of lower bars come first
        out.append({"top_over_lower": uv[:n][seen[:n]], "own": uv[n:][seen[n:]]})
    return out


def lower_mat_of(samples: list[Sample]) -> list[np.ndarray]:
    """:func:`lower_mat_crossings` of samples from any datasets (each sample's ``dataset``), each image
    file placed once however often it is listed; a sample that names no dataset has none."""
    by_root: dict[Path | None, dict[str, Sample]] = {}  # each file's first sample, by dataset
    for s in samples:
        by_root.setdefault(s.dataset, {}).setdefault(str(s.path), s)
    found = {path: np.zeros((0, 2)) for path in by_root.pop(None, {})}
    for root, these in by_root.items():
        found.update(zip(these, lower_mat_crossings(root, list(these.values())), strict=True))
    return [found[str(s.path)] for s in samples]


class _Camera:
    """One image's pinhole camera, to find chords in view and where two sets of chords cross in it."""

    def __init__(self, world_from_camera: np.ndarray, s: Sample) -> None:
        self.world_from_camera = world_from_camera
        self.centre = world_from_camera[:3, 3]
        self.intrinsics = s.intrinsics

    def _project(self, points: np.ndarray) -> Projection:
        return project(points, self.world_from_camera, self.intrinsics)

    def visible(self, chords: np.ndarray) -> np.ndarray:
        """The chords (N, 2, 3) with both ends in front of the camera and one near the frame."""
        pr = self._project(chords.reshape(-1, 3))
        w, h = self.intrinsics.width, self.intrinsics.height
        margin = 0.1 * max(w, h)
        u, v = pr.u.reshape(-1, 2), pr.v.reshape(-1, 2)
        inside = (u > -margin) & (u < w + margin) & (v > -margin) & (v < h + margin)
        return chords[(pr.depth_m.reshape(-1, 2) > 0.05).all(1) & inside.any(1)]

    def cross(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where chords ``a`` and ``b`` cross in the image, inside the frame: (K, 2) pixels and (K,) the
        camera depth of the nearer of the two bars there."""
        if not len(a) or not len(b):
            return np.zeros((0, 2)), np.zeros(0)
        ra, rb = a - self.centre, b - self.centre
        na = np.cross(ra[:, 0], ra[:, 1])  # normal of the plane through the camera and chord a
        nb = np.cross(rb[:, 0], rb[:, 1])
        fb = np.einsum("ik,jek->ije", na, rb)  # (A, B, 2): sides of b's ends to a's plane
        fa = np.einsum("jk,iek->ije", nb, ra)
        hit = (fb[..., 0] * fb[..., 1] < 0) & (fa[..., 0] * fa[..., 1] < 0)
        i, j = np.nonzero(hit)
        tb = fb[i, j, 0] / (fb[i, j, 0] - fb[i, j, 1])
        ta = fa[i, j, 0] / (fa[i, j, 0] - fa[i, j, 1])
        pb = self._project(b[j, 0] + tb[:, None] * (b[j, 1] - b[j, 0]))
        pa = self._project(a[i, 0] + ta[:, None] * (a[i, 1] - a[i, 0]))
        keep = pb.in_image
        return np.c_[pb.u, pb.v][keep], np.minimum(pa.depth_m, pb.depth_m)[keep]


def _chords(root: Path) -> _Chords:
    """The top mat of the dataset's mesh as chords, with the mat surface through its crossings."""
    config = read_info(root).get("config")
    if not isinstance(config, dict) or "mesh" not in config:
        raise ConfigError(
            f"{root}: meta/info.json records no mesh config, so its lower mat cannot be placed; accepted: "
            "a dataset written by `rebar dataset build`"
        )
    cfg = validate(MeshConfig, mesh_sections(Path(root), config), str(root))
    if cfg.mesh.kind == "ifc":  # the top mat's pieces, with their directions along the fitted surface
        rm = build_rebar_mesh(cfg)
        layout, crossings = rm.layout, rm.crossings
        bars = [b for b in layout.bars if b.layer == layout.surface.top_mat] or layout.bars
    else:
        layout = build_layout(cfg)
        crossings = find_crossings(layout, cfg.mesh.crossing_tolerance_m)
        bars = layout.bars
    surf = MatSurface.of_crossings(layout, crossings)
    ends, direction = [], []
    for bar in bars:
        pts = sample(bar.curve, CHORD_M)[1]
        ends.append(np.stack([pts[:-1], pts[1:]], axis=1))
        direction.append(np.full(len(pts) - 1, bar.direction))
    e = np.concatenate(ends)
    ab, height = surf.to_ab(e.reshape(-1, 3)).reshape(-1, 2, 2), surf.height(e.reshape(-1, 3)).reshape(-1, 2)
    return _Chords(surf, e, ab, height, np.concatenate(direction))


def _seen(s: Sample, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Which of the crossings at pixels ``uv`` (the nearer bar at camera depth ``z``) the image shows: the
    depth image (uint16 millimetres, 0 = none) sees about ``z`` there, and the instance map shows the lower
    mat (a distractor: :func:`~rebar_data.perception.evaluation.data.read_distractors`) nearby."""
    keep = np.ones(len(uv), bool)
    j, i = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    if s.depth_path is not None:
        depth = read_uint16(s.depth_path, "a 16-bit depth PNG in millimetres")
        d = depth[np.clip(i, 0, depth.shape[0] - 1), np.clip(j, 0, depth.shape[1] - 1)].astype(float) / 1000.0
        keep &= (d > 0) & (np.abs(d - z) <= DEPTH_TOLERANCE_M)
    lower = read_distractors(s)
    if lower is not None:
        h, w = lower.shape
        fx = s.camera[0] if s.camera else 0.0
        for k in np.nonzero(keep)[0]:
            r = int(np.ceil(fx * 0.01 / max(z[k], 1e-3) + REACH_PX))
            keep[k] = lower[
                max(i[k] - r, 0) : min(i[k] + r + 1, h), max(j[k] - r, 0) : min(j[k] + r + 1, w)
            ].any()
    return keep
