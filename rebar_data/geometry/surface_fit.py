"""The surface a mesh's bars span, fitted to their centerlines, and the bars' mats along its normal.

A mesh read from IFC has no ``face`` or ``layers``: cameras, lights and the top mat come from this fit.

Surface. The centerlines are sampled every ``SAMPLE_STEP_M``. A plane is fitted by PCA (the normal is the
direction of least spread); a cylinder by least squares on the distance to an axis, started from each of the
plane's two in-plane axes, on ``FIT_POINTS`` of the samples. ``surface: auto`` takes the cylinder when it fits
better (a smaller RMS residual), fewer pieces run through the thickness measured from it than from the plane
(see Mats: the bars lie along it) and its radius is under ``MAX_RADIUS_EXTENTS`` times the bars' extent; else,
and on a tie, the plane. Both fits' RMS and largest residuals are kept (``plane_rms_m``, ``plane_max_m``,
``cylinder_rms_m``, ``cylinder_max_m``).

Camera side. ``camera_side`` (a direction in the model's frame, before ``pose`` moves it) picks the side of
the surface the camera looks from: the normal at the bars' centre that points along it. Without it: for a
plane, the side with a positive z component (from above), or for a plane within about 6 degrees of vertical
(|n_z| < 0.1) the side with a positive x component, then y, both in the model's frame; for a cylinder, its
outside (away from the axis). Being the model's, the side moves with the model wherever ``pose`` (or a servo
world) puts it.

Mats. A piece's height is its signed distance above the surface towards the camera side. A piece whose
heights span at most half of ``mat_gap_m`` lies in a mat (a bar along the surface); one spanning more runs
through the thickness (a stirrup's leg, a U-bar's bend) and belongs to no mat (layer -1). The in-mat pieces'
mean heights, sorted from the camera side, start a new mat wherever two neighbours differ by more than
``mat_gap_m`` (default: twice the largest bar diameter, so a mat's two touching bar directions stay one
mat). Mat 0 is the nearest the camera side; the top mat the robot ties is mat ``top_mat`` (default 0).

Faces (:func:`fit_faces`). Bars on several faces (a cage: four walls round a lift shaft's core) fit no one
surface: cameras would look through two walls and no piece would lie in a mat. A face is found from the
bars that cross: each piece's normal is the plane its tangent spans with the tangents of the other bars'
pieces that touch it (within the two radii and a quarter of ``mat_gap_m``, at ``FACE_ANGLE_DEG`` or more;
the main direction of those planes' normals). Pieces are grouped by normal (the direction most of the bar
length lies within ``FACE_ANGLE_DEG`` of, then the next), and a group split where the pieces' offsets along
the normal jump by more than ``FACE_GAP_M`` (opposite walls); a face holds at least ``MIN_FACE_SHARE`` of the
length. A piece that crosses nothing joins the face whose plane is nearest (all of it within ``FACE_GAP_M``),
else none. The faces are taken when there are two or more and their planes leave less than
``FACE_RMS_RATIO`` of the one surface's RMS residual (a slab, a wall and a tunnel stay one surface); each
face is then a plane with its own mats, seen from outside the cage (away from the bars' centre). The face
cameras and lights face is the one whose outside ``camera_side`` points to most, else the one with the most
bar length (inside ``mesh.bbox_m`` when one is set); its mats are the pieces' layers, and pieces of the
other faces are in no mat (-1), so ``top_mat`` is that face's outer mat.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from rebar_data.config import ConfigError
from rebar_data.geometry.curves import Curve, CurveArrays

SAMPLE_STEP_M = 0.02
FIT_POINTS = 4000  # the cylinder is fitted to this many of the samples, evenly spread along the centerlines
MAX_RADIUS_EXTENTS = 100.0
VERTICAL_NZ = 0.1
_SIDE_MIN_COS = 1e-3
FACE_CHUNK_M = 0.1  # pieces are cut into chunks this long to find the bars that cross them
FACE_ANGLE_DEG = 30.0  # crossing tangents at a smaller angle span no plane; normals within it share a face
FACE_GAP_M = 0.5  # pieces sharing a normal, further apart than this along it, lie on different faces
MIN_FACE_SHARE = 0.1  # a face holds at least this share of the centerline length
FACE_RMS_RATIO = 0.5  # faces are taken when their planes leave less than this share of one surface's RMS


@dataclass(frozen=True)
class Mat:
    """One mat: its pieces' mean height above the surface, the band their heights span and how many."""

    height_m: float
    low_m: float
    high_m: float
    pieces: int


@dataclass(frozen=True)
class SurfaceFit:
    """A plane or cylinder through the bars, its camera side, and the bars' mats.

    ``world_from_surface``: for a plane, origin at the bars' centroid, z the camera-side normal, x the
    direction the bars spread most; for a cylinder, origin on the axis, x along it, z towards the bars'
    centre. ``side`` is +1 when the camera side of a cylinder is its outside, -1 inside (1 for a plane).
    """

    kind: str  # "plane" | "cylinder"
    world_from_surface: np.ndarray
    radius_m: float  # cylinder; 0 for a plane
    side: int
    plane_rms_m: float
    plane_max_m: float
    cylinder_rms_m: float | None  # None where no cylinder was fitted
    cylinder_max_m: float | None
    mat_gap_m: float
    mats: list[Mat]
    piece_mat: np.ndarray  # (pieces,) mat index of each piece, -1 for pieces through the thickness
    top_mat: int
    camera_side: str  # how the side was chosen

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (N,) of world points above the surface, towards the camera side."""
        T = self.world_from_surface
        local = (np.atleast_2d(points) - T[:3, 3]) @ T[:3, :3]
        if self.kind == "plane":
            return local[:, 2]
        return self.side * (np.linalg.norm(local[:, 1:], axis=1) - self.radius_m)

    def normal(self, points: np.ndarray) -> np.ndarray:
        """Camera-side unit normal (N, 3) of the surface at (or beside) world points."""
        T = self.world_from_surface
        local = (np.atleast_2d(points) - T[:3, 3]) @ T[:3, :3]
        if self.kind == "plane":
            return np.tile(T[:3, 2], (len(local), 1))
        radial = local.copy()
        radial[:, 0] = 0.0
        norm = np.linalg.norm(radial, axis=1, keepdims=True)
        radial = np.where(norm > 0, radial / np.where(norm > 0, norm, 1.0), [0.0, 0.0, 1.0])
        return self.side * radial @ T[:3, :3].T

    def record(self) -> dict:
        """What mesh.json says about the fit."""
        return {
            "kind": self.kind,
            "radius_m": self.radius_m,
            "camera_side": self.camera_side,
            "normal_at_centre": [float(x) for x in self.side * self.world_from_surface[:3, 2]],
            "plane_rms_m": self.plane_rms_m,
            "plane_max_m": self.plane_max_m,
            "cylinder_rms_m": self.cylinder_rms_m,
            "cylinder_max_m": self.cylinder_max_m,
            "mat_gap_m": self.mat_gap_m,
            "mats": [m.__dict__ for m in self.mats],
            "top_mat": self.top_mat,
            "pieces_through": int((self.piece_mat < 0).sum()),
        }


def _samples(curves: list[Curve], arrays: CurveArrays | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points along every curve, ends included, at most ``SAMPLE_STEP_M`` apart, and the index of the curve
    each belongs to (``arrays``: the curves' arrays, when the caller has them)."""
    arrays = CurveArrays.of(curves) if arrays is None else arrays
    counts = np.maximum(2, np.ceil(arrays.length / SAMPLE_STEP_M).astype(np.int64) + 1)
    owner = np.repeat(np.arange(len(curves)), counts)
    k = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
    s = arrays.length[owner] * k / (counts[owner] - 1)
    return arrays.point(owner, s), owner


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid, in-plane axes (2, 3) by decreasing spread, and unit normal of the least-squares plane."""
    centroid = points.mean(0)
    d = points - centroid
    _, vectors = np.linalg.eigh(d.T @ d)  # ascending spread: the normal first
    return centroid, vectors[:, [2, 1]].T, vectors[:, 0]


def _circle(uv: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kasa) circle through 2D points: centre and radius."""
    A = np.column_stack([2.0 * uv, np.ones(len(uv))])
    b = (uv**2).sum(1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    centre = sol[:2]
    return centre, float(np.sqrt(max(sol[2] + centre @ centre, 0.0)))


def _basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(axis, u)


def cylinder_residuals(points: np.ndarray, p: np.ndarray, axis: np.ndarray, radius: float) -> np.ndarray:
    """Distance of each point from the axis through ``p`` along unit ``axis``, less ``radius``."""
    d = points - p
    return np.linalg.norm(d - np.outer(d @ axis, axis), axis=1) - radius


def fit_cylinder(points: np.ndarray, axis0: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Least-squares cylinder started with its axis along ``axis0``: axis point, unit axis, radius and the
    residuals (distance to the axis less the radius) of every point."""
    centroid = points.mean(0)
    u, w = _basis(axis0)
    rel = points - centroid
    c2, r0 = _circle(np.column_stack([rel @ u, rel @ w]))
    p0 = centroid + c2[0] * u + c2[1] * w

    def unpack(x):
        axis = axis0 + x[0] * u + x[1] * w
        axis = axis / np.linalg.norm(axis)
        return p0 + x[2] * u + x[3] * w, axis, x[4]

    def residual(x):
        return cylinder_residuals(points, *unpack(x))

    sol = least_squares(residual, np.array([0.0, 0.0, 0.0, 0.0, r0]), x_scale="jac", method="trf")
    p, axis, r = unpack(sol.x)
    return p, axis, float(abs(r)), residual(sol.x)


def _side_sign(normal: np.ndarray, camera_side: np.ndarray | None, what: str) -> tuple[int, str]:
    if camera_side is not None:
        v = np.asarray(camera_side, float)
        cos = float(normal @ v / np.linalg.norm(v))
        if abs(cos) < _SIDE_MIN_COS:
            raise ConfigError(
                f"mesh.camera_side = {[float(x) for x in v]} lies in the fitted {what} (normal "
                f"{np.round(normal, 4).tolist()}); accepted: a direction with a component along that normal"
            )
        return (1 if cos > 0 else -1), f"mesh.camera_side {[float(x) for x in v]}"
    return 0, ""


def _plane_side(normal: np.ndarray) -> tuple[int, str]:
    if abs(normal[2]) >= VERTICAL_NZ:
        return (1 if normal[2] > 0 else -1), "up (+z)"
    for k, name in ((0, "+x"), (1, "+y")):
        if abs(normal[k]) > 1e-9:
            return (1 if normal[k] > 0 else -1), f"{name} (a surface within 6 degrees of vertical)"
    return 1, "+z"


def _span(heights: np.ndarray, owner: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest height (n,) of each piece's samples."""
    lo, hi = np.full(n, np.inf), np.full(n, -np.inf)
    np.minimum.at(lo, owner, heights)
    np.maximum.at(hi, owner, heights)
    return lo, hi


def _through(heights: np.ndarray, owner: np.ndarray, n: int, gap: float) -> int:
    """How many pieces span more than half of ``gap`` in height: those that lie along no mat."""
    lo, hi = _span(heights, owner, n)
    return int(np.sum(hi - lo > gap / 2.0))


def fit_surface(
    curves: list[Curve],
    diameters_m: np.ndarray,
    *,
    surface: str = "auto",
    camera_side: tuple[float, float, float] | None = None,
    mat_gap_m: float | None = None,
    top_mat: int | None = None,
    need_mats: bool = False,
    world_from_model: np.ndarray | None = None,
) -> SurfaceFit:
    """Fit one surface to ``curves`` (the pieces of a mesh, in the world) and find their mats (module doc).

    ``need_mats``: a mesh without a mat (no piece along the surface) is a ConfigError, not an empty list.
    ``world_from_model``: the rotation (3x3) of the pose that placed ``curves``; the camera side is chosen in
    the model's frame."""
    R = np.eye(3) if world_from_model is None else np.asarray(world_from_model, float)[:3, :3]
    points, owner = _samples(curves)
    gap = float(mat_gap_m) if mat_gap_m is not None else 2.0 * float(np.max(diameters_m))
    fit = _fit_one(points, owner, len(curves), gap, surface=surface, camera_side=camera_side, R=R)
    return check_mats(fit, need_mats=need_mats, top_mat=top_mat)


def _fit_one(
    points: np.ndarray,
    owner: np.ndarray,
    n_curves: int,
    gap: float,
    *,
    surface: str,
    camera_side: tuple[float, float, float] | None,
    R: np.ndarray,
    outward_from: np.ndarray | None = None,
) -> SurfaceFit:
    """One surface through the samples of ``n_curves`` pieces, its camera side and mats (module doc); a plane
    without ``camera_side`` faces away from ``outward_from`` when it is given (a face of a cage)."""
    centroid, in_plane, n = fit_plane(points)
    plane_res = (points - centroid) @ n
    plane_rms, plane_max = float(np.sqrt(np.mean(plane_res**2))), float(np.abs(plane_res).max())
    extent = float(np.linalg.norm(points.max(0) - points.min(0)))
    cyl = None
    if surface in ("auto", "cylinder") and len(points) >= 6:
        some = points[np.unique(np.linspace(0, len(points) - 1, min(len(points), FIT_POINTS)).astype(int))]
        fits = [fit_cylinder(some, a) for a in in_plane]
        p, axis, radius, _ = min(fits, key=lambda f: float(np.mean(f[3] ** 2)))
        cyl = (p, axis, radius, cylinder_residuals(points, p, axis, radius))
    cyl_rms = float(np.sqrt(np.mean(cyl[3] ** 2))) if cyl is not None else None
    cyl_max = float(np.abs(cyl[3]).max()) if cyl is not None else None
    if surface == "cylinder" and cyl is None:
        raise ConfigError(
            f"mesh.surface = cylinder: {len(points)} centerline points are too few to fit one; accepted: surface: "
            "plane or auto"
        )
    T = np.eye(4)
    use_cylinder = surface == "cylinder"
    if cyl is not None:
        p, axis, radius, residual = cyl
        foot = p + ((centroid - p) @ axis) * axis
        out = centroid - foot
        if np.linalg.norm(out) < 1e-9 * max(extent, 1e-9):
            if surface == "cylinder":
                raise ConfigError(
                    "mesh.surface = cylinder: the bars' centre lies on the fitted axis, which leaves no side to "
                    "look from; accepted: surface: plane or auto"
                )
        elif surface == "auto" and radius < MAX_RADIUS_EXTENTS * extent and cyl_rms < plane_rms:
            k = n_curves
            use_cylinder = _through(residual, owner, k, gap) < _through(plane_res, owner, k, gap)
    if use_cylinder:
        out /= np.linalg.norm(out)
        sign, how = _side_sign(R.T @ out, camera_side, "cylinder")
        if sign == 0:
            sign, how = 1, "the cylinder's outside"
        T[:3, 0], T[:3, 2] = axis, out
        T[:3, 1] = np.cross(out, axis)
        T[:3, 3] = foot
        kind = "cylinder"
    else:
        sign, how = _side_sign(R.T @ n, camera_side, "plane")
        if sign == 0 and outward_from is not None:
            sign, how = (
                (1 if n @ (centroid - outward_from) >= 0.0 else -1),
                "outside the cage (away from its centre)",
            )
        if sign == 0:
            sign, how = _plane_side(R.T @ n)
        z = sign * n
        T[:3, 0], T[:3, 2] = in_plane[0], z
        T[:3, 1] = np.cross(z, in_plane[0])
        T[:3, 3] = centroid
        kind, radius, sign = "plane", 0.0, 1
    fit = SurfaceFit(
        kind,
        T,
        float(radius),
        int(sign),
        plane_rms,
        plane_max,
        cyl_rms,
        cyl_max,
        gap,
        [],
        np.zeros(0),
        0,
        how,
    )
    mats, piece_mat = _mats(fit.height(points), owner, n_curves, gap)
    return replace(fit, mats=mats, piece_mat=piece_mat)


def check_mats(fit: SurfaceFit, *, need_mats: bool, top_mat: int | None) -> SurfaceFit:
    """``fit`` with its top mat set; a ConfigError when ``need_mats`` and no piece lies along it, or when
    ``top_mat`` names a mat it does not have."""
    mats, kind, gap = fit.mats, fit.kind, fit.mat_gap_m
    if not mats and need_mats:
        raise ConfigError(
            f"mesh: no bar lies along the fitted {kind} (every piece spans more than half of mat_gap_m = "
            f"{gap:g} m in height); accepted: a larger mesh.mat_gap_m, or mesh.surface set to the other shape"
        )
    top = 0 if top_mat is None else int(top_mat)
    if top >= len(mats) and (mats or top_mat is not None):
        found = "; ".join(f"{k}: {m.pieces} pieces at {m.height_m:+.4f} m" for k, m in enumerate(mats))
        raise ConfigError(
            f"mesh.top_mat = {top_mat}: the bars form {len(mats)} mat{'s' if len(mats) != 1 else ''} counted "
            f"from the camera side ({found or 'no piece lies along the surface'}); accepted: "
            + (f"0 to {len(mats) - 1}" if mats else "no top_mat, or a larger mat_gap_m")
        )
    return replace(fit, top_mat=top)


@dataclass(frozen=True)
class Faces:
    """The faces of a mesh (one for a slab, a wall or a tunnel; several for a cage), each fitted on its own.

    ``fits[k]`` is face k's surface, camera side and mats, over its own pieces; ``piece_face`` the face of
    each piece (-1: on none, such as a bar of a wall whose crossing bars were filtered out); ``chosen`` the face cameras and lights face, whose mats give the pieces' layers.
    """

    fits: list[SurfaceFit]
    piece_face: np.ndarray  # (pieces,)
    chosen: int
    how: str  # how the face was chosen
    piece_mat: np.ndarray  # (pieces,) mat in the chosen face; -1 through its thickness or on another face

    @property
    def surface(self) -> SurfaceFit:
        return self.fits[self.chosen]

    def normal(self, points: np.ndarray, pieces: np.ndarray) -> np.ndarray:
        """Camera-side unit normal (N, 3) at world points, each of its piece's face."""
        out = np.zeros((len(points), 3))
        faces = np.asarray(self.piece_face[pieces])
        faces = np.where(faces < 0, self.chosen, faces)  # a piece on no face: the chosen face's side
        for k, fit in enumerate(self.fits):
            on = faces == k
            if np.any(on):
                out[on] = fit.normal(points[on])
        return out

    def record(self) -> list[dict]:
        """What mesh.json says about each face."""
        return [
            {**fit.record(), "pieces": int(np.sum(self.piece_face == k)), "chosen": k == self.chosen}
            for k, fit in enumerate(self.fits)
        ]


def _hemisphere(n: int = 600) -> np.ndarray:
    """``n`` directions spread evenly over the half sphere z >= 0 (a Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    z = k / n
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _chunk_distance(
    a: np.ndarray, u: np.ndarray, ha: np.ndarray, b: np.ndarray, v: np.ndarray, hb: np.ndarray
):
    """Distance (N,) between segments ``a + s u`` (|s| <= ha) and ``b + t v`` (|t| <= hb), u and v unit."""
    w = a - b
    uv, uw, vw = np.einsum("ij,ij->i", u, v), np.einsum("ij,ij->i", u, w), np.einsum("ij,ij->i", v, w)
    den = 1.0 - uv * uv
    s = np.where(den > 1e-12, (uv * vw - uw) / np.where(den > 1e-12, den, 1.0), 0.0)
    s = np.clip(s, -ha, ha)
    t = np.clip(uv * s + vw, -hb, hb)
    s = np.clip(uv * t - uw, -ha, ha)
    return np.linalg.norm(w + s[:, None] * u - t[:, None] * v, axis=1)


def _piece_normals(arrays: CurveArrays, bar_of: np.ndarray, pads: np.ndarray) -> np.ndarray:
    """Each piece's normal (N, 3; NaN for a piece no other bar crosses): the plane spanned by its tangent and
    the tangents of the other bars' pieces that cross it (within the two pads, at ``FACE_ANGLE_DEG`` or more).
    Pieces are cut into chunks of at most ``FACE_CHUNK_M`` (a quarter of an arc's radius), each taken as the
    segment along its middle tangent."""
    n_curves = len(arrays.length)
    chunk = np.where(arrays.is_arc, np.minimum(FACE_CHUNK_M, arrays.radius / 4.0), FACE_CHUNK_M)
    counts = np.maximum(1, np.ceil(arrays.length / chunk).astype(np.int64))
    owner = np.repeat(np.arange(n_curves), counts)
    half = np.repeat(arrays.length / counts / 2.0, counts)
    k = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
    s_mid = (2.0 * k + 1.0) * half
    centres = arrays.point(owner, s_mid)
    tangents = arrays.tangent(owner, s_mid)
    reach = half + pads[owner]
    pairs = cKDTree(centres).query_pairs(2.0 * float(reach.max()), output_type="ndarray")
    normals = np.full((n_curves, 3), np.nan)
    if len(pairs) == 0:
        return normals
    p, q = pairs[:, 0], pairs[:, 1]
    keep = (bar_of[owner[p]] != bar_of[owner[q]]) & (
        np.linalg.norm(centres[p] - centres[q], axis=1) <= reach[p] + reach[q]
    )
    p, q = p[keep], q[keep]
    n = np.cross(tangents[p], tangents[q])
    norm = np.linalg.norm(n, axis=1)
    keep = norm >= np.sin(np.radians(FACE_ANGLE_DEG))
    p, q, n, norm = p[keep], q[keep], n[keep], norm[keep]
    keep = (
        _chunk_distance(centres[p], tangents[p], half[p], centres[q], tangents[q], half[q])
        <= pads[owner[p]] + pads[owner[q]]
    )
    p, q = p[keep], q[keep]
    n = n[keep] / norm[keep, None]
    tensor = np.einsum("ni,nj->nij", n, n)
    sums = np.zeros((n_curves, 3, 3))
    for side in (p, q):
        np.add.at(sums, owner[side], tensor)
    has = np.einsum("nii->n", sums) > 0.0
    if np.any(has):
        _, vectors = np.linalg.eigh(sums[has])
        normals[has] = vectors[:, :, 2]  # the direction most of its crossings' normals share
    return normals


def _face_groups(arrays: CurveArrays, normals: np.ndarray) -> list[np.ndarray]:
    """Pieces grouped into faces (module doc, Faces): by normal, then by offset along it; each group holds at
    least ``MIN_FACE_SHARE`` of the length. Pieces of no group are left out."""
    valid = np.all(np.isfinite(normals), axis=1)
    lengths = arrays.length
    total = float(lengths.sum())
    mids = arrays.point(np.arange(len(lengths)), lengths / 2.0)
    dirs = _hemisphere()
    cos_max = np.cos(np.radians(FACE_ANGLE_DEG))
    left = valid.copy()
    groups: list[np.ndarray] = []
    while True:
        w = np.where(left, lengths, 0.0)
        if w.sum() < MIN_FACE_SHARE * total:
            break
        idx = np.flatnonzero(left)
        score = (np.abs(normals[idx] @ dirs.T) >= cos_max).T @ w[idx]
        d = dirs[int(np.argmax(score))]
        members = idx[np.abs(normals[idx] @ d) >= cos_max]
        tensor = np.einsum("n,ni,nj->ij", lengths[members], normals[members], normals[members])
        d = np.linalg.eigh(tensor)[1][:, 2]
        members = idx[np.abs(normals[idx] @ d) >= cos_max]
        if lengths[members].sum() < MIN_FACE_SHARE * total:
            break
        left[members] = False
        offset = mids[members] @ d
        order = np.argsort(offset, kind="stable")
        breaks = np.flatnonzero(np.diff(offset[order]) > FACE_GAP_M) + 1
        for part in np.split(members[order], breaks):
            if lengths[part].sum() >= MIN_FACE_SHARE * total:
                groups.append(np.sort(part))
    return groups


def _assign_rest(points: np.ndarray, owner: np.ndarray, groups: list[np.ndarray], n: int) -> np.ndarray:
    """Each piece's face: its group's, else the face whose plane lies nearest its samples (by their mean
    distance) with every sample within ``FACE_GAP_M`` of it, else none (-1)."""
    face = np.full(n, -1, np.int64)
    for k, g in enumerate(groups):
        face[g] = k
    rest = np.flatnonzero(face < 0)
    if len(rest) == 0:
        return face
    in_rest = np.isin(owner, rest)
    pos = np.searchsorted(rest, owner[in_rest])
    counts = np.bincount(pos, minlength=len(rest))
    mean = np.full((len(rest), len(groups)), np.inf)
    for k, g in enumerate(groups):
        centroid, _, normal = fit_plane(points[np.isin(owner, g)])
        d = np.abs((points[in_rest] - centroid) @ normal)
        far = np.zeros(len(rest), bool)
        np.logical_or.at(far, pos, d > FACE_GAP_M)
        mean[:, k] = np.where(far, np.inf, np.bincount(pos, weights=d, minlength=len(rest)) / counts)
    best = np.argmin(mean, axis=1)
    face[rest] = np.where(np.isfinite(mean[np.arange(len(rest)), best]), best, -1)
    return face


def fit_faces(
    curves: list[Curve],
    diameters_m: np.ndarray,
    *,
    bar_of: np.ndarray,
    surface: str = "auto",
    camera_side: tuple[float, float, float] | None = None,
    mat_gap_m: float | None = None,
    top_mat: int | None = None,
    need_mats: bool = False,
    world_from_model: np.ndarray | None = None,
    preference: np.ndarray | None = None,
) -> Faces:
    """The faces of ``curves`` (the pieces of a mesh, in the world; ``bar_of`` each one's bar), each with its
    own surface and mats, and the face cameras face (module doc, Faces).

    ``preference``: a weight per piece (default its length); without ``camera_side`` the face of the largest
    sum is chosen. The other arguments as :func:`fit_surface`'s; ``need_mats`` and ``top_mat`` are checked
    on the chosen face."""
    R = np.eye(3) if world_from_model is None else np.asarray(world_from_model, float)[:3, :3]
    diameters_m = np.asarray(diameters_m, float)
    n = len(curves)
    arrays = CurveArrays.of(curves)
    points, owner = _samples(curves, arrays)
    gap = float(mat_gap_m) if mat_gap_m is not None else 2.0 * float(np.max(diameters_m))
    single = _fit_one(points, owner, n, gap, surface=surface, camera_side=None, R=R)
    lengths = arrays.length
    groups = []
    if surface != "cylinder" and n >= 2:
        groups = _face_groups(
            arrays, _piece_normals(arrays, np.asarray(bar_of), diameters_m / 2.0 + gap / 4.0)
        )
    fits: list[SurfaceFit] = []
    if len(groups) >= 2:
        face = _assign_rest(points, owner, groups, n)
        centre = points.mean(0)
        members = [np.flatnonzero(face == k) for k in range(len(groups))]
        squares, counted = 0.0, 0
        for idx in members:
            on = np.isin(owner, idx)
            local = np.searchsorted(idx, owner[on])
            fit = _fit_one(
                points[on], local, len(idx), gap, surface="plane", camera_side=None, R=R, outward_from=centre
            )
            fits.append(fit)
            squares, counted = squares + fit.plane_rms_m**2 * int(on.sum()), counted + int(on.sum())
        one_rms = single.cylinder_rms_m if single.kind == "cylinder" else single.plane_rms_m
        if np.sqrt(squares / counted) >= FACE_RMS_RATIO * one_rms:
            fits = []  # one surface fits about as well: not a cage
    if not fits:
        if camera_side is not None:
            single = _fit_one(points, owner, n, gap, surface=surface, camera_side=camera_side, R=R)
        fit = check_mats(single, need_mats=need_mats, top_mat=top_mat)
        return Faces([fit], np.zeros(n, np.int64), 0, "one surface", fit.piece_mat)
    weight = lengths if preference is None else np.asarray(preference, float)
    if camera_side is not None:
        v = R @ (np.asarray(camera_side, float) / np.linalg.norm(camera_side))
        chosen = int(np.argmax([f.world_from_surface[:3, 2] @ v for f in fits]))
        how = f"the face whose outside mesh.camera_side {[float(x) for x in camera_side]} points to most"
    else:
        chosen = int(np.argmax([weight[idx].sum() for idx in members]))
        how = "the face with the most bar length" + (" in mesh.bbox_m" if preference is not None else "")
    fits[chosen] = check_mats(fits[chosen], need_mats=need_mats, top_mat=top_mat)
    piece_mat = np.full(n, -1, np.int32)
    piece_mat[members[chosen]] = fits[chosen].piece_mat
    return Faces(fits, face, chosen, f"{how}: {chosen} of {len(fits)}", piece_mat)


def _mats(heights: np.ndarray, owner: np.ndarray, n_pieces: int, gap: float) -> tuple[list[Mat], np.ndarray]:
    """The mats, from the camera side, and each piece's mat (-1: through the thickness), from the heights of
    the samples of every piece (module doc, Mats)."""
    lo, hi = _span(heights, owner, n_pieces)
    mean = np.bincount(owner, weights=heights, minlength=n_pieces) / np.bincount(owner, minlength=n_pieces)
    flat = hi - lo <= gap / 2.0
    piece_mat = np.full(n_pieces, -1, np.int32)
    mats: list[Mat] = []
    order = [i for i in np.argsort(-mean, kind="stable") if flat[i]]
    group: list[int] = []
    for i in order + [None]:
        if i is not None and (not group or mean[group[-1]] - mean[i] <= gap):
            group.append(i)
            continue
        if group:
            piece_mat[group] = len(mats)
            mats.append(
                Mat(float(np.mean(mean[group])), float(lo[group].min()), float(hi[group].max()), len(group))
            )
        group = [i] if i is not None else []
    return mats, piece_mat
