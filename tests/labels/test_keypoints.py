from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from rebar_data.camera import Intrinsics, project, rigid_inverse
from rebar_data.geometry.build import build_rebar_mesh
from rebar_data.geometry.config import MeshConfig
from rebar_data.labels.keypoints import CrossingParts, label_frame


def K() -> Intrinsics:
    """The Kinect v1 preset's intrinsics."""
    return Intrinsics(640, 480, 525.0, 525.0, 320.0, 240.0)


def _look_down(height: float, x: float = 0.0, y: float = 0.0) -> np.ndarray:
    """Camera above the slab looking straight down (-z), image x along world x."""
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
    T[:3, 3] = [x, y, height]
    return T


def _tensor_mesh(m):
    return o3d.t.geometry.TriangleMesh(
        o3d.core.Tensor(np.asarray(m.vertices, np.float32)), o3d.core.Tensor(np.asarray(m.faces, np.int32))
    )


def _caster(rm, extra=None):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(_tensor_mesh(rm.mesh))
    ids = [rm.triangle_part_id]
    if extra is not None:
        scene.add_triangles(_tensor_mesh(extra))

    def cast(origins, dirs):
        rays = o3d.core.Tensor(np.c_[origins, dirs].astype(np.float32))
        r = scene.cast_rays(rays)
        geom = r["geometry_ids"].numpy()
        prim = r["primitive_ids"].numpy()
        inst = np.full(len(origins), -1, np.int32)
        hit0 = geom == 0
        inst[hit0] = ids[0][prim[hit0]]
        inst[geom == 1] = -3
        return r["t_hit"].numpy().astype(float), inst

    return cast


@pytest.fixture(scope="module")
def slab():
    cfg = MeshConfig.model_validate(
        {
            "seed": 1,
            "mesh": {"kind": "planar", "width_m": 1.0, "height_m": 0.6},
            "realism": {"tie_wire_fraction": 0.5},
        }
    )
    return build_rebar_mesh(cfg)


def test_projection_matches_the_pinhole_formula():
    T = _look_down(1.0, 0.1, 0.2)
    pts = np.array([[0.1, 0.2, 0.0], [0.3, 0.2, 0.5], [0.0, 0.0, 2.0]])
    p = project(pts, T, Intrinsics(640, 480, 500.0, 510.0, 320.0, 240.0))
    np.testing.assert_allclose(p.point_camera[0], [0, 0, 1.0], atol=1e-15)
    np.testing.assert_allclose([p.u[0], p.v[0]], [320, 240])
    np.testing.assert_allclose([p.u[1], p.v[1]], [320 + 500 * 0.2 / 0.5, 240])
    assert list(p.in_image) == [True, True, False]  # the last one is behind the camera
    np.testing.assert_allclose(rigid_inverse(T) @ T, np.eye(4), atol=1e-15)


def test_top_view_sees_every_crossing_in_the_frame(slab):
    T = _look_down(1.2)
    lab = label_frame(slab, CrossingParts.of(slab), T, K(), _caster(slab))
    inside = (lab.u >= 0) & (lab.u < 640) & (lab.v >= 0) & (lab.v < 480)
    assert inside.sum() > 20
    assert np.all(lab.visibility[inside] == 2)
    assert np.all(lab.visibility[~inside] == 0)
    # boxes follow the rule: 4 bar diameters at the crossing's depth
    np.testing.assert_allclose(lab.box_size_px[inside], 4 * 525 * 0.012 / lab.depth_m[inside])


def test_an_occluder_makes_crossings_occluded(slab):
    import trimesh

    T = _look_down(1.2)
    board = trimesh.creation.box(extents=[0.25, 0.25, 0.01])
    board.apply_translation([0.0, 0.0, 0.5])  # between camera and slab, over the centre
    lab = label_frame(slab, CrossingParts.of(slab), T, K(), _caster(slab, board))
    c = slab.crossings.point
    # rays from the camera to crossings within ~0.2 m of the centre pass through the board
    behind = np.hypot(c[:, 0], c[:, 1]) < 0.15
    assert behind.any()
    assert np.all(lab.visibility[behind] == 1)
    assert np.all(lab.hit_instance[behind] == -3)
    assert np.sum(lab.visibility == 2) > 10


def test_grazing_view_finds_crossings_hidden_behind_nearer_bars(slab):
    e = np.radians(8.0)
    fwd = np.array([1.0, 0.0, -np.tan(e)])
    fwd /= np.linalg.norm(fwd)
    right = np.array([0.0, -1.0, 0.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([right, np.cross(fwd, right), fwd], axis=1)
    T[:3, 3] = [-0.9, 0.0, 0.9 * np.tan(e)]
    parts = CrossingParts.of(slab)
    lab = label_frame(slab, parts, T, K(), _caster(slab))
    hidden = lab.visibility == 1
    assert hidden.sum() >= 10 and (lab.visibility == 2).sum() >= 10
    # what hides them is rebar (another bar, or their own bar far from the crossing, seen along it)
    assert np.all(lab.hit_instance[hidden] >= 0)
    seen = lab.visibility == 2
    assert np.all(np.any(lab.hit_instance[seen][:, None] == parts.own[seen], axis=1))


def _oblique(tilt_deg: float) -> np.ndarray:
    """Camera 0.6 m from the slab's centre, tilted ``tilt_deg`` from the normal about the world y axis."""
    t = np.radians(tilt_deg)
    fwd = np.array([np.sin(t), 0.0, -np.cos(t)])
    right = np.array([0.0, -1.0, 0.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([right, np.cross(fwd, right), fwd], axis=1)
    T[:3, 3] = -0.6 * fwd
    return T


def _centerlines_crossing_px(rm, parts, i: int, T: np.ndarray) -> np.ndarray:
    """Where the two projected centerlines of crossing ``i`` meet in the image (homogeneous lines)."""
    lines = []
    for p, t in (
        (rm.crossings.point_a[i], parts.tangent_a[i]),
        (rm.crossings.point_b[i], parts.tangent_b[i]),
    ):
        ends = project(np.stack([p - 0.02 * t, p + 0.02 * t]), T, K())
        lines.append(np.cross(np.r_[ends.u[0], ends.v[0], 1.0], np.r_[ends.u[1], ends.v[1], 1.0]))
    x = np.cross(*lines)
    return x[:2] / x[2]


def test_labels_sit_where_the_projected_centerlines_cross(slab):
    parts = CrossingParts.of(slab)
    T = _oblique(35.0)
    lab = label_frame(slab, parts, T, K(), _caster(slab))
    seen = np.flatnonzero(lab.visibility == 2)
    assert len(seen) > 20
    mid = project(slab.crossings.point, T, K())
    shift = []
    for i in seen:
        np.testing.assert_allclose(
            [lab.u[i], lab.v[i]], _centerlines_crossing_px(slab, parts, i, T), atol=1e-6
        )
        shift.append(np.hypot(lab.u[i] - mid.u[i], lab.v[i] - mid.v[i]))
    # the hidden midpoint projects px away at 35 degrees (bar radius * sin(angle) * f / z)
    assert np.median(shift) > 1.0
    # the sight point is on the nearer bar's centerline: the bar on top, seen from above
    c = slab.crossings
    for i in seen[:10]:
        q = np.array([lab.point_world[i]])
        on_a = abs(np.cross(q[0] - c.point_a[i], parts.tangent_a[i])).max()
        on_b = abs(np.cross(q[0] - c.point_b[i], parts.tangent_b[i])).max()
        nearer_a = c.point_a[i] @ c.normal[i] > c.point_b[i] @ c.normal[i]
        assert (on_a if nearer_a else on_b) < 1e-9


def test_seen_along_the_normal_the_label_is_the_crossing(slab):
    parts = CrossingParts.of(slab)
    c = slab.crossings
    i = int(np.argmin(np.hypot(c.point[:, 0], c.point[:, 1])))
    T = _look_down(0.6, *c.point[i, :2])
    lab = label_frame(slab, parts, T, K(), _caster(slab))
    mid = project(c.point[i : i + 1], T, K())
    assert lab.visibility[i] == 2
    assert np.hypot(lab.u[i] - mid.u[0], lab.v[i] - mid.v[0]) < 1e-6


def test_grazing_views_label_where_the_bars_cross_or_not_at_all(slab):
    """At a grazing view the ray that meets both centerlines runs far along them: the label stays where the
    projected centerlines cross (not at the crossing's own point, which projects into the gap between the
    bars' images); where the projected bars meet at a shallow angle no pixel is the crossing's, and the
    keypoint is at most occluded."""
    from rebar_data.labels.keypoints import SIGHT_MIN_ANGLE_DEG, sight_lines, sight_points

    parts = CrossingParts.of(slab)
    c = slab.crossings
    centre = np.array([-0.9, 0.05, 0.02])  # a camera almost in the mat's plane
    q, seen = sight_points(slab, parts, centre)
    _, _, sine, _ = sight_lines(c.point_a, parts.tangent_a, c.point_b, parts.tangent_b, centre)
    shallow = sine < np.sin(np.radians(SIGHT_MIN_ANGLE_DEG))
    assert shallow.any() and seen.any() and not seen[shallow].any()
    np.testing.assert_array_equal(q[~seen], c.point[~seen])  # no crossing pixel: the crossing's own point
    off = np.linalg.norm(q - c.point, axis=1)
    assert (off[seen] > 3 * parts.diameter_max_m[seen]).any()  # kept however far along the bars it runs

    # a camera that sees these crossings: a shallow-angle one is labelled, but not as visible
    fwd = c.point.mean(axis=0) - centre
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, np.cross(fwd, right), fwd], axis=1)
    T[:3, 3] = centre
    lab = label_frame(slab, parts, T, K(), _caster(slab))
    assert (lab.visibility[~seen] <= 1).all()
    assert (lab.visibility[seen] == 2).any()


def _off_centerline(curve, q: np.ndarray) -> float:
    """How far ``q`` is from ``curve`` (or from its straight extension past an end)."""
    s = curve.project(q)
    p, t = curve.point(s), curve.tangent(s)
    return float(np.linalg.norm(np.cross(q - p, t)))


def test_sight_points_on_curved_bars_lie_on_both_centerlines():
    """On arcs the sight point is found again on the tangent lines at the points found: it ends on the
    nearer bar's centerline and on the ray through the farther one, also at a grazing view."""
    from rebar_data.labels.keypoints import sight_points

    cfg = MeshConfig.model_validate(
        {
            "seed": 2,
            "mesh": {
                "kind": "tunnel_segment",
                "intrados_arc_m": 0.9,  # 3 m radius, 0.3 rad: the paper's curvature on a smaller element
                "extrados_arc_m": 0.99,
                "width_m": 0.8,
                "thickness_m": 0.3,
            },
        }
    )
    rm = build_rebar_mesh(cfg)
    parts = CrossingParts.of(rm)
    c = rm.crossings
    centre = c.point.mean(axis=0) + np.array([0.0, 0.9, 0.05])  # well off to one side: a grazing view
    q, seen = sight_points(rm, parts, centre)
    assert seen.sum() > 20
    far = []
    for i in np.flatnonzero(seen):
        a, b = rm.bars[c.bar_a[i]].curve, rm.bars[c.bar_b[i]].curve
        d_a, d_b = _off_centerline(a, q[i]), _off_centerline(b, q[i])
        farther = b if d_a < d_b else a
        assert min(d_a, d_b) < 1e-6  # on the nearer bar's centerline, not its tangent line at the crossing
        # the ray from the camera through q meets the farther centerline (or its straight extension, for
        # a crossing at a bar's end): the distance between the ray and the tangent line there is 0
        ray = (q[i] - centre) / np.linalg.norm(q[i] - centre)
        s = farther.project(q[i])
        for _ in range(5):
            p, t = farther.point(s), farther.tangent(s)
            n = np.cross(ray, t)
            gap = abs(np.dot(p - centre, n)) / np.linalg.norm(n)
            # the tangent line's point nearest the ray, then the curve's point nearest that
            w = p - centre
            b, d, e = np.dot(ray, t), np.dot(ray, w), np.dot(t, w)
            s = farther.project(p + t * ((b * d - e) / (1.0 - b * b)))
        assert gap < 1e-6
        far.append(np.linalg.norm(q[i] - c.point[i]))
    assert max(far) > 0.03  # some run centimetres along the bars, where a tangent line would be off
