"""``rebar dataset audit``: label-quality checks on a built dataset, with a report and pictures.

Checks (each with its measured figure and bar):
- reprojection: visible/occluded labels equal the projection of their 3D point with the stored camera
  (max error <= 1e-3 px, depth within 1e-6 m), and visibility 0 exactly when the point projects outside;
- formats: YOLO, COCO and Parquet hold the same visible keypoints;
- geometry: the 3D points are the crossings of the mesh rebuilt from the recorded config;
- instance pass: visible keypoints land on one of their own parts, occluded ones on something else
  (not applicable to a dataset built without its depth or instance maps; see :func:`check_instances`);
- duplicates: no two images are identical;
- leakage: no scene or trajectory in two splits (unless the split rule is random).
Plots of the distributions and a contact sheet are written beside the report.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from rebar_data.dataset import layout
from rebar_data.dataset.layout import INSTANCE_OFFSET, DatasetInfo

REPROJECTION_MAX_PX = 1e-3
DEPTH_MAX_M = 1e-6
FORMAT_MAX_PX = 1e-6
GEOMETRY_MAX_M = 1e-9
SIGHT_MAX_M = (
    1e-3  # sight points are on tangent lines: an arc departs by s^2 / 2R (0.13 mm at 30 mm, R 3.2 m)
)
SIGHT_SAMPLES = 2000  # sight points checked per dataset
VISIBLE_ON_OWN_MIN = 0.99  # share of visible keypoints whose pixel (3x3) shows one of their parts
OCCLUDED_OFF_OWN_MIN = 0.95  # share of occluded keypoints whose pixel shows something else
# share of visible keypoints whose own pixel (the one the label lies in, not the 3x3 around it) shows one of
# their parts at their depth: a label between two bars' images (on the ground seen between them) fails it,
# where the 3x3 check above still finds a bar's edge beside it (1-5% of the wide sets' visible labels before
# dataset versions 1.1.0: 0.964 on wide-tunnel-a 1.0.0, where visible_on_own_bar gave 0.994)
VISIBLE_AT_OWN_DEPTH_MIN = 0.99
AT_DEPTH_DIAMETERS = 2.0  # the bar's surface lies up to a diameter in front of the centerline's sight point


@dataclass
class Check:
    """One audit check. ``applicable`` false: the check does not apply to this dataset (its bar says why);
    it then counts as passed and its value means nothing."""

    name: str
    passed: bool
    value: float
    bar: str
    detail: str
    applicable: bool = True


def load_tables(ds: Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    return layout.read_table(ds / layout.SAMPLES).to_pandas(), layout.read_table(
        ds / layout.KEYPOINTS
    ).to_pandas()


def check_reprojection(S: pd.DataFrame, K: pd.DataFrame) -> list[Check]:
    s = S.set_index("image_id")
    worst_px, worst_z, wrong_vis = 0.0, 0.0, 0
    for iid, g in K.groupby("image_id", sort=False):
        row = s.loc[iid]
        T = np.asarray(row.world_from_camera, float).reshape(4, 4)
        P = g[["x_world", "y_world", "z_world"]].to_numpy(float)
        pc = (P - T[:3, 3]) @ T[:3, :3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = row.fx * pc[:, 0] / z + row.cx
            v = row.fy * pc[:, 1] / z + row.cy
        inside = (z > 0) & (u >= 0) & (u < row.width) & (v >= 0) & (v < row.height)
        vis = g["visibility"].to_numpy()
        wrong_vis += int(np.sum((vis > 0) != inside))
        m = vis > 0
        if m.any():
            err = np.hypot(u[m] - g["u"].to_numpy()[m], v[m] - g["v"].to_numpy()[m])
            worst_px = max(worst_px, float(err.max()))
            worst_z = max(worst_z, float(np.abs(z[m] - g["depth_m"].to_numpy()[m]).max()))
    return [
        Check(
            "reprojection_px",
            worst_px <= REPROJECTION_MAX_PX,
            worst_px,
            f"<= {REPROJECTION_MAX_PX} px",
            "largest distance between a label and the projection of its 3D point",
        ),
        Check(
            "reprojection_depth_m",
            worst_z <= DEPTH_MAX_M,
            worst_z,
            f"<= {DEPTH_MAX_M} m",
            "largest difference between depth_m and the camera-frame z of the 3D point",
        ),
        Check(
            "visibility_vs_frame",
            wrong_vis == 0,
            wrong_vis,
            "0",
            "keypoints whose visibility (0 vs >0) disagrees with projecting inside the image",
        ),
    ]


def _yolo_points(ds: Path, S: pd.DataFrame) -> dict[str, np.ndarray]:
    """Visible keypoints per image from the YOLO files (an image whose file is missing is left out)."""
    out = {}
    for row in S.itertuples():
        p = ds / layout.label_path(row.split, row.image_id)
        if not p.exists():
            continue
        txt = p.read_text().split()
        vals = np.array(txt, float).reshape(-1, 8) if txt else np.zeros((0, 8))
        out[row.image_id] = np.c_[vals[:, 5] * row.width, vals[:, 6] * row.height, vals[:, 7]]
    return out


def _coco_points(ds: Path) -> dict[str, np.ndarray]:
    pts: dict[str, list] = {}
    for split in layout.SPLITS:
        d = json.loads((ds / layout.coco_path(split)).read_text())
        key = {im["id"]: Path(im["file_name"]).stem for im in d["images"]}
        for k in key.values():
            pts.setdefault(k, [])
        for a in d["annotations"]:
            pts[key[a["image_id"]]].append(a["keypoints"][:3])
    return {k: np.array(v, float).reshape(-1, 3) for k, v in pts.items()}


def _sorted(p: np.ndarray) -> np.ndarray:
    return p[np.lexsort((p[:, 1], p[:, 0]))] if len(p) else p


def check_formats(ds: Path, S: pd.DataFrame, K: pd.DataFrame) -> Check:
    yolo, coco = _yolo_points(ds, S), _coco_points(ds)
    vis = K[K.visibility == 2]
    table = {iid: g[["u", "v", "visibility"]].to_numpy(float) for iid, g in vis.groupby("image_id")}
    worst, mismatched = 0.0, []
    for iid in S.image_id:
        t = _sorted(table.get(iid, np.zeros((0, 3))))
        for name, pts in (("yolo", yolo.get(iid)), ("coco", coco.get(iid))):
            p = _sorted(pts if pts is not None else np.zeros((0, 3)))
            if len(p) != len(t) or (len(p) and np.any(p[:, 2] != t[:, 2])):
                mismatched.append(f"{iid} ({name})")
                continue
            if len(p):
                worst = max(worst, float(np.abs(p[:, :2] - t[:, :2]).max()))
    ok = not mismatched and worst <= FORMAT_MAX_PX
    detail = "YOLO, COCO and Parquet hold the same visible keypoints"
    if mismatched:
        detail += f"; they differ for {len(mismatched)} images, e.g. {mismatched[0]}"
    return Check("formats_agree_px", ok, worst, f"<= {FORMAT_MAX_PX} px, same keypoints", detail)


def check_geometry(info: DatasetInfo, K: pd.DataFrame, ds: Path | None = None):
    """Rebuild the mesh from the recorded config (a mesh read from IFC from the dataset's own copy of the
    model, ``meta/mesh.ifc``); the table's crossing points must be its crossings, and every sight point must
    lie on one of its crossing's two bar centerlines (or be the crossing's point, in a grazing view)."""
    from rebar_data.geometry.build import build_rebar_mesh
    from rebar_data.geometry.config import MeshConfig

    # only the mesh sections: the rendering sections may have gained or lost options since the build
    if ds is None:
        mesh_keys = {k: info.config[k] for k in ("seed", "mesh", "realism", "pose") if k in info.config}
    else:
        mesh_keys = layout.mesh_sections(ds, info.config)
    rm = build_rebar_mesh(MeshConfig.model_validate(mesh_keys))
    first = K[K.image_id == K.image_id.iloc[0]].sort_values("crossing_id")
    ok_count = len(first) == len(rm.crossings)
    err = sight_err = float("inf")
    if ok_count:
        err = float(
            np.abs(first[["x_crossing", "y_crossing", "z_crossing"]].to_numpy() - rm.crossings.point).max()
        )
        # every sight point is on one of its crossing's two centerlines (their tangent lines: an arc departs
        # from its tangent by micrometres over the few millimetres a sight point moves)
        inview = K[np.isfinite(K.u)]
        step = max(1, len(inview) // SIGHT_SAMPLES)
        sight = inview[["x_world", "y_world", "z_world"]].to_numpy(float)[::step]
        cid = inview.crossing_id.to_numpy()[::step]
        from rebar_data.labels.keypoints import CrossingParts

        parts = CrossingParts.of(rm)  # a bar of several pieces: the piece nearest the sight point
        sight_err = max(
            (
                min(
                    float(parts.nearest_on_bar(parts.piece_a[[i]], q[None])[2][0]),
                    float(parts.nearest_on_bar(parts.piece_b[[i]], q[None])[2][0]),
                    float(
                        np.linalg.norm(q - rm.crossings.point[i])
                    ),  # grazing views fall back to the crossing
                )
                for q, i in zip(sight, cid, strict=True)
            ),
            default=0.0,
        )
    check = Check(
        "geometry_m",
        ok_count and err <= GEOMETRY_MAX_M and sight_err <= SIGHT_MAX_M,
        max(err, sight_err),
        f"crossings <= {GEOMETRY_MAX_M} m, sight points <= {SIGHT_MAX_M} m off a centerline",
        f"{len(rm.crossings)} crossings in the rebuilt mesh, {len(first)} rows per image; crossing points "
        f"off by {err:.1e} m, sight points {sight_err:.1e} m from their bar's centerline",
    )
    return check, rm


class _PixelAlong:
    """Distance along its bar from a crossing's sight point to the surface point seen at a pixel (inf: not
    its part)."""

    def __init__(
        self, rm, parts, inst: np.ndarray, depth: np.ndarray, world_from_camera: np.ndarray, k: tuple
    ):
        self.rm, self.parts, self.inst, self.depth, self.T, self.k = (
            rm,
            parts,
            inst,
            depth,
            world_from_camera,
            k,
        )

    def __call__(self, crossing: int, y: int, x: int, sight: np.ndarray) -> float:
        from rebar_data.labels.keypoints import along_bar_distance

        z = self.depth[y, x]
        if z <= 0:
            return float("inf")
        fx, fy, cx, cy = self.k
        p_cam = np.array([(x + 0.5 - cx) / fx * z, (y + 0.5 - cy) / fy * z, z])
        point = self.T[:3, :3] @ p_cam + self.T[:3, 3]
        return along_bar_distance(self.rm, self.parts, crossing, int(self.inst[y, x]), point, sight)


PASS_CHECKS = {  # name -> (visibility checked, bar, what agreeing means)
    "visible_on_own_bar": (
        2,
        VISIBLE_ON_OWN_MIN,
        "visible keypoints showing one of their own parts near the crossing",
    ),
    "occluded_off_own_bar": (
        1,
        OCCLUDED_OFF_OWN_MIN,
        "occluded keypoints showing something else or their bar far away",
    ),
    "visible_at_own_depth": (
        2,
        VISIBLE_AT_OWN_DEPTH_MIN,
        f"visible keypoints whose own pixel shows one of their parts within {AT_DEPTH_DIAMETERS:g} bar diameters "
        "of their depth",
    ),
}


def check_instances(
    ds: Path, S: pd.DataFrame, K: pd.DataFrame, rm, *, stored: dict[str, bool] | None = None
) -> list[Check]:
    """The rendered passes, independently of the labels' ray cast, must agree with each keypoint's
    visibility: a visible keypoint shows one of its own parts near the crossing in the 3x3 pixels around
    it; an occluded one shows something else, or its own bar far from the crossing, there. "Near" is measured
    along the bar from the keypoint's sight point, as the labels do, to the pixel's surface point (depth
    pass, back-projected). A keypoint occluded because no pixel shows its bars cross (its sight point is
    the crossing's own point: :func:`rebar_data.labels.keypoints.sight_points`) is counted apart. And a
    visible keypoint's own pixel shows one of its parts at about its depth (``visible_at_own_depth``).

    A check never passes on nothing checked. What happens instead depends on why there was nothing:

    - the dataset chose not to store a pass (``stored``, the config's ``dataset.store_depth`` and
      ``store_instances``; each check reads both maps): the checks are *not applicable*, reported as such
      (``applicable`` false, bar "not applicable (...)"); they do not fail a dataset built that way on purpose;
    - the config stores both passes but rows name no map, or a map that does not read: those images are lost
      data, and every check fails, its detail counting them ("nothing checked" when no image had maps);
    - the maps are there but the dataset holds no keypoint of the kind a check reads: no visible keypoint
      fails (such a dataset has nothing to learn from); no occluded keypoint a pixel could show is not
      applicable (a view of a mat with neither tie wire nor lower mat can have none).
    """
    stored = stored or {"store_depth": True, "store_instances": True}
    not_stored = [k for k, v in stored.items() if not v]
    if not_stored:
        why = " and ".join(f"dataset.{k}: false" for k in not_stored)
        return [
            Check(
                name,
                True,
                0.0,
                f"not applicable ({why})",
                f"the dataset stores no maps to check {what}",
                False,
            )
            for name, (_, _, what) in PASS_CHECKS.items()
        ]
    from rebar_data.labels.keypoints import CrossingParts, LabelRule

    parts = CrossingParts.of(rm)
    near_m = LabelRule().near_diameters * parts.diameter_max_m
    slack_m = parts.diameter_max_m  # a pixel centre is up to 0.7 px from the label
    hits = {1: [0, 0], 2: [0, 0]}  # visibility -> [agreeing, total]
    unseen = at_own = without_maps = 0
    for row in S.itertuples():
        maps = _read_maps(ds, row)
        if maps is None:
            without_maps += 1
            continue
        inst, depth = maps
        T = np.asarray(row.world_from_camera, float).reshape(4, 4)
        h, w = inst.shape
        along = _PixelAlong(rm, parts, inst, depth, T, (row.fx, row.fy, row.cx, row.cy))

        for kp in K[(K.image_id == row.image_id) & (K.visibility > 0)].itertuples():
            x, y, c = int(np.floor(kp.u)), int(np.floor(kp.v)), kp.crossing_id
            sight = np.array([kp.x_world, kp.y_world, kp.z_world])
            window = [
                (yy, xx)
                for yy in range(max(y - 1, 0), min(y + 2, h))
                for xx in range(max(x - 1, 0), min(x + 2, w))
            ]
            if kp.visibility == 2:
                agree = any(along(c, yy, xx, sight) <= near_m[c] + slack_m[c] for yy, xx in window)
                z = depth[y, x]
                at_own += bool(
                    parts.is_own(rm, c, int(inst[y, x]))
                    and abs(z - kp.depth_m) <= AT_DEPTH_DIAMETERS * parts.diameter_max_m[c]
                )
            elif (kp.x_world, kp.y_world, kp.z_world) == (kp.x_crossing, kp.y_crossing, kp.z_crossing):
                unseen += 1  # no pixel shows the bars cross (labels.keypoints.sight_points): occluded by rule
                continue
            else:  # an occluder's edge can pass within the 0.7 px between the label and a pixel centre
                agree = any(along(c, yy, xx, sight) > near_m[c] - slack_m[c] for yy, xx in window)
            hits[kp.visibility][0] += agree
            hits[kp.visibility][1] += 1
    agreeing = {
        "visible_on_own_bar": hits[2][0],
        "occluded_off_own_bar": hits[1][0],
        "visible_at_own_depth": at_own,
    }
    return [
        _pass_check(
            name, agreeing[name], hits[vis][1], unseen=unseen, without_maps=without_maps, images=len(S)
        )
        for name, (vis, _, _) in PASS_CHECKS.items()
    ]


def _pass_check(name: str, agree: int, total: int, *, unseen: int, without_maps: int, images: int) -> Check:
    """One rendered-pass check from its counts (see :func:`check_instances` for what nothing checked gives)."""
    vis, bar, what = PASS_CHECKS[name]
    more = f"; {unseen} more occluded where no pixel shows the bars cross (not checked)" if vis == 1 else ""
    detail = f"{agree} of {total} {what}{more}"
    # a share check (not the depth one) passes with one disagreement whatever share it leaves: with a handful
    # checked (a few occluded keypoints in a set) one sub-pixel tie wire in front of the labels' exact ray,
    # missed by the rendered pass, would otherwise decide the check
    one_off = name != "visible_at_own_depth"
    bar_text = f">= {bar}" + (" or 1 off" if one_off else "")
    share = agree / total if total else 0.0
    if without_maps:
        nothing = "nothing checked: " if without_maps == images else ""
        lost = (
            f"{nothing}{without_maps} of {images} images have no readable depth or instance map, though the "
            "config stores them (dataset.store_depth and store_instances are true)"
        )
        return Check(name, False, share, bar_text, f"{lost}; {detail}")
    if total == 0 and vis == 1:
        return Check(name, True, 0.0, "not applicable (no occluded keypoint a pixel shows)", detail, False)
    if total == 0:
        return Check(
            name, False, 0.0, bar_text, f"nothing checked: the dataset has no visible keypoint ({detail})"
        )
    passed = share >= bar or (one_off and total - agree <= 1)
    return Check(name, passed, share, bar_text, detail)


def _read_maps(ds: Path, row) -> tuple[np.ndarray, np.ndarray] | None:
    """The instance ids and the depth in metres of an image, or None when its row names no map or one does
    not read."""
    if not isinstance(row.instance_file, str) or not isinstance(row.depth_file, str):
        return None
    inst = cv2.imread(str(ds / row.instance_file), cv2.IMREAD_UNCHANGED)
    depth = cv2.imread(str(ds / row.depth_file), cv2.IMREAD_UNCHANGED)
    if inst is None or depth is None:
        return None
    return inst.astype(np.int32) - INSTANCE_OFFSET, depth.astype(np.float64) / 1000.0


def check_duplicates(ds: Path, S: pd.DataFrame) -> Check:
    from rebar_data.digest import sha256_file

    digests = [sha256_file(ds / f) for f in S.file_name]
    dup = len(digests) - len(set(digests))
    return Check("duplicate_images", dup == 0, dup, "0", "images whose bytes equal another image's")


def check_leakage(info: DatasetInfo, S: pd.DataFrame) -> list[Check]:
    out = []
    for col, noun in (("scene_id", "scenes"), ("trajectory_id", "trajectories")):
        n = int((S.groupby(col)["split"].nunique() > 1).sum())
        rule = info.split.get("rule")
        applies = rule != "random" and (col == "trajectory_id" or rule == "scene")
        out.append(
            Check(
                f"{col}_in_two_splits",
                n == 0 or not applies,
                n,
                "0" if applies else "not applicable (split rule)",
                f"{noun} present in more than one split (split rule: {rule})",
                applies,
            )
        )
    return out


def audit_dataset(
    ds: Path, *, out: Path | None = None, contact_sheet_images: int = 24
) -> tuple[list[Check], dict]:
    """Run every check, write ``report.json``, ``report.md``, plots and the contact sheet to ``out`` (by
    default the dataset's own ``audit/``); the dataset itself is only read."""
    from rebar_data.dataset.audit_plots import (
        contact_sheet,
        distribution_plots,
        sensor_depth_sheet,
        sensor_depth_stats,
        split_parameters,
    )

    ds = Path(ds)
    info = DatasetInfo.read(ds)
    S, K = load_tables(ds)
    checks = check_reprojection(S, K)
    checks.append(check_formats(ds, S, K))
    geo, rm = check_geometry(info, K, ds)
    checks.append(geo)
    options = info.config.get("dataset", {})
    stored = {k: bool(options.get(k, True)) for k in ("store_depth", "store_instances")}
    checks += check_instances(ds, S, K, rm, stored=stored)
    checks.append(check_duplicates(ds, S))
    checks += check_leakage(info, S)
    out = Path(out) if out is not None else ds / layout.AUDIT_DIR
    out.mkdir(parents=True, exist_ok=True)
    stats = distribution_plots(S, K, out)
    _, constant = split_parameters(S)
    contact_sheet(ds, S, K, out / "contact_sheet.png", n=contact_sheet_images)
    sensor_depth = sensor_depth_stats(ds, S)
    if sensor_depth:
        stats["sensor_depth"] = sensor_depth
        sensor_depth_sheet(ds, S, out / "sensor_depth.png")
    report = {
        "dataset": f"{info.name} v{info.version}",
        "passed": all(c.passed for c in checks),
        "checks": [asdict(c) for c in checks],
        "stats": stats,
        "constant_parameters": constant,
    }
    (out / "report.json").write_text(json.dumps(report, indent=2, sort_keys=True, default=float) + "\n")
    (out / "report.md").write_text(_markdown(info, checks, stats, constant))
    return checks, stats


def result_word(passed: bool, applicable: bool = True) -> str:
    """``n/a``, ``pass`` or ``FAIL``: how a check's result is written in the report, the CLI and the card."""
    return "n/a" if not applicable else "pass" if passed else "FAIL"


def _markdown(info: DatasetInfo, checks: list[Check], stats: dict, constant: dict) -> str:
    lines = [
        f"# Audit of {info.name} v{info.version}",
        "",
        "| check | result | value | bar | what |",
        "|---|---|---|---|---|",
    ]
    for c in checks:
        lines.append(
            f"| {c.name} | {result_word(c.passed, c.applicable)} | {f'{c.value:.6g}' if c.applicable else '-'} | {c.bar} | {c.detail} |"
        )
    lines += ["", "## Distributions", ""]
    for k, v in stats.items():
        if k != "sensor_depth":
            lines.append(f"- {k}: {v}")
    if stats.get("sensor_depth"):
        lines += [
            "",
            "## Sensor depth",
            "",
            "Share of the pixels with a surface that the depth sensor measured, and its median absolute",
            "difference from the exact depth where both have a value (the labels are checked against the exact",
            "depth):",
            "",
            "| model | images | measured (mean) | measured (min-max) | median abs error (mm) |",
            "|---|---|---|---|---|",
        ]
        for model, m in stats["sensor_depth"].items():
            lines.append(
                f"| {model} | {m['images']} | {m['valid_fraction_mean']:.3f} | "
                f"{m['valid_fraction_min']:.3f}-{m['valid_fraction_max']:.3f} | {m['abs_error_median_mm']} |"
            )
        lines += ["", "![sensor depth beside its colour frame and the exact depth](sensor_depth.png)"]
    lines += [
        "",
        "![keypoints per image](keypoints_per_image.png)",
        "![visibility](visibility.png)",
        "![randomized parameters that vary](coverage.png)",
        "",
        "## Constant parameters",
        "",
        "Randomized parameters with one value in every image (not drawn in coverage.png):",
        "",
    ]
    lines += [f"- `{k}` = {json.dumps(v)}" for k, v in constant.items()] or ["- none"]
    lines += [
        "",
        "![contact sheet](contact_sheet.png)",
        "",
    ]
    return "\n".join(lines)
