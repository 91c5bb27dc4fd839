"""The one pinhole camera (``rebar_data.camera``): projection, pixel rays, the pose convention and the point
feature's interaction matrix."""

from __future__ import annotations

import numpy as np
import pytest

from rebar_data.camera import Intrinsics, point_interaction_matrix, project, rigid_inverse

CAM = Intrinsics(640, 480, 500.0, 510.0, 321.5, 238.25)  # fx != fy, principal point off centre


def _rotation(axis_angle: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: the rotation of ``axis_angle`` (axis times angle, radians)."""
    angle = np.linalg.norm(axis_angle)
    if angle == 0:
        return np.eye(3)
    k = axis_angle / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


def _pose(axis_angle, centre) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _rotation(np.asarray(axis_angle, float)), centre
    return T


def test_a_known_point_projects_by_the_pinhole_formula():
    uv = CAM.project(np.array([[0.2, -0.1, 0.5], [0.0, 0.0, 2.0], [0.1, 0.1, -1.0], [0.1, 0.1, 0.0]]))
    np.testing.assert_allclose(uv[0], [500.0 * 0.4 + 321.5, 510.0 * -0.2 + 238.25])  # (521.5, 136.25)
    np.testing.assert_array_equal(uv[1], [321.5, 238.25])  # the optical axis: the principal point
    assert np.isnan(uv[2:]).all()  # behind the camera, or in its plane: no pixel
    np.testing.assert_allclose(CAM.normalized(uv[:1]), [[0.4, -0.2]], atol=1e-15)
    np.testing.assert_allclose(CAM.back_project(uv[:1], np.array([0.5])), [[0.2, -0.1, 0.5]], atol=1e-15)
    np.testing.assert_array_equal(CAM.K @ [0.4, -0.2, 1.0], [521.5, 136.25, 1.0])


def test_a_world_point_projects_through_world_from_camera():
    """A camera 1 m above the origin looking down (-z): its x axis along the world's x, y along -y."""
    T = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1.0], [0, 0, 0, 1]])
    p = project(np.array([[0.1, 0.2, 0.0], [0.0, 0.0, 1.5], [2.0, 0.0, 0.0]]), T, CAM)
    np.testing.assert_allclose(p.point_camera, [[0.1, -0.2, 1.0], [0.0, 0.0, -0.5], [2.0, 0.0, 1.0]])
    np.testing.assert_allclose([p.u[0], p.v[0]], [321.5 + 50.0, 238.25 - 102.0])
    np.testing.assert_allclose(p.depth_m, [1.0, -0.5, 1.0])
    assert np.isnan(p.u[1]) and np.isnan(p.v[1])
    assert list(p.in_image) == [True, False, False]  # behind the camera; in front but left of the frame


def test_the_pose_convention_columns_are_the_camera_axes_and_centre():
    T = _pose([0.3, -0.5, 0.2], [0.4, -0.1, 1.2])
    np.testing.assert_allclose(T @ [0.0, 0.0, 0.0, 1.0], [0.4, -0.1, 1.2, 1.0])  # the centre
    np.testing.assert_allclose(T @ [0.0, 0.0, 2.0, 1.0], [*(T[:3, 3] + 2.0 * T[:3, 2]), 1.0])  # 2 m ahead
    inv = rigid_inverse(T)
    np.testing.assert_allclose(inv @ T, np.eye(4), atol=1e-15)
    np.testing.assert_allclose(inv, np.linalg.inv(T), atol=1e-15)
    ahead = T[:3, 3] + 0.7 * T[:3, 2] + 0.1 * T[:3, 0]  # 0.7 m along z, 0.1 m to the right: x > 0, u > cx
    p = project(ahead[None], T, CAM)
    np.testing.assert_allclose(p.point_camera, [[0.1, 0.0, 0.7]], atol=1e-15)
    np.testing.assert_allclose([p.u[0], p.v[0]], [321.5 + 500.0 * 0.1 / 0.7, 238.25])


def test_rays_through_pixel_centres_hit_back_the_same_pixel():
    cam = Intrinsics(7, 5, 6.0, 6.5, 3.2, 2.4)
    rays = cam.pixel_rays()
    assert rays.shape == (35, 3)
    np.testing.assert_array_equal(rays[:, 2], 1.0)
    i, j = np.divmod(np.arange(35), 7)  # row-major
    np.testing.assert_allclose(rays[[0, -1], :2], [[-0.45, -1.9 / 6.5], [0.55, 2.1 / 6.5]])  # corners' pixels
    for depth in (0.3, 2.0):
        np.testing.assert_allclose(cam.project(depth * rays), np.c_[j + 0.5, i + 0.5], atol=1e-12)
    unit = cam.pixel_rays(unit=True)
    np.testing.assert_allclose(np.linalg.norm(unit, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(cam.project(unit), np.c_[j + 0.5, i + 0.5], atol=1e-12)
    # cells of 4 pixels: the rays through their centres (4j + 2, 4i + 2), ceil(7 / 4) x ceil(5 / 4) of them
    grid = cam.ray_grid(4)
    assert grid.shape == (2, 2, 2)
    np.testing.assert_allclose(grid[:, 1, 0], [(2.0 - 3.2) / 6.0, (6.0 - 2.4) / 6.5])
    np.testing.assert_allclose(cam.project(np.r_[grid[:, 1, 1], 1.0]), [[6.0, 6.0]])


def test_resized_and_mirrored_images_keep_each_point_on_its_pixel():
    P = np.array([[0.12, -0.07, 0.9], [-0.3, 0.2, 1.4]])
    uv = CAM.project(P)
    half = CAM.resized(320, 120)
    assert half == Intrinsics(320, 120, 250.0, 127.5, 160.75, 59.5625)
    np.testing.assert_allclose(half.project(P), uv * [0.5, 0.25])
    mirror = CAM.mirrored()
    assert (mirror.cx, mirror.cy, mirror.fx) == (640 - 321.5, 238.25, 500.0)
    np.testing.assert_allclose(mirror.project(P * [-1.0, 1.0, 1.0]), np.c_[640.0 - uv[:, 0], uv[:, 1]])


def test_fields_of_view():
    fov = Intrinsics(640, 480, 320.0, 240.0, 320.0, 240.0).fov_deg
    np.testing.assert_allclose(fov, [90.0, 90.0])


def _seen(cam: Intrinsics, P: np.ndarray, twist: np.ndarray, t: float) -> np.ndarray:
    """The pixel of the still camera-frame point ``P`` once the camera has moved with a pure translation
    or rotation ``twist`` (v, w) for ``t`` seconds."""
    then_from_now = _pose(twist[3:] * t, twist[:3] * t)
    return cam.project((rigid_inverse(then_from_now) @ np.r_[P, 1.0])[:3])[0]


@pytest.mark.parametrize("x, y, Z", [(0.0, 0.0, 0.6), (0.25, -0.15, 0.8), (-0.4, 0.3, 1.7)])
def test_the_interaction_matrix_is_the_derivative_of_the_projection(x, y, Z):
    """L (v, w) is d(x, y)/dt of a still point while the camera moves with twist (v, w) in its own frame:
    compared, column by column, with a central difference of the point's projection along that motion."""
    P = np.array([x * Z, y * Z, Z])
    cam = Intrinsics(640, 480, 1.0, 1.0, 0.0, 0.0)  # pixels are normalised coordinates
    L = point_interaction_matrix(x, y, Z)
    assert L.shape == (2, 6)
    h = 1e-6
    for k, twist in enumerate(np.eye(6)):
        ahead, behind = _seen(cam, P, twist, h), _seen(cam, P, twist, -h)
        np.testing.assert_allclose((ahead - behind) / (2 * h), L[:, k], atol=1e-7)
    np.testing.assert_array_equal(L[:, 0], [-1.0 / Z, 0.0])  # moving right, the point moves left in view
