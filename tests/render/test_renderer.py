"""Renderer tests: projection convention, exact ids and depth, determinism, reuse. One renderer for all."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from rebar_data.camera import Intrinsics
from rebar_data.geometry.solids import Part
from rebar_data.render.renderer import Renderer
from rebar_data.scene.cameras import look_at
from rebar_data.scene.config import RenderConfig, SceneConfig
from rebar_data.scene.sample import sample_scene
from rebar_data.scene.surroundings import build_surroundings
from tests.render.test_sensor import OFF

K = Intrinsics(320, 240, 300.0, 310.0, 157.3, 121.6)  # a principal point off the pixel grid on purpose


@pytest.fixture(scope="module")
def renderer(tmp_path_factory):
    r = Renderer(K, RenderConfig(texture_size_px=256, cache_dir=tmp_path_factory.mktemp("textures")))
    yield r
    r.close()


def _scene(seed=0, **changes):
    s = sample_scene(SceneConfig(), np.random.default_rng(seed))
    return replace(s, **changes)


def _quiet(s):
    """No distractors, the ground far below."""
    d = replace(s.distractors, lower_layer=False, spacers=0, loose_tie_wire=0, formwork_sides=0)
    return replace(s, distractors=d, ground=replace(s.ground, distance_m=2.0, shape="plane"))


def _sphere_rm(base_rm, centre, radius):
    s = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    s.apply_translation(centre)
    part = Part(0, "tie_wire", -1, -1, s)
    return replace(base_rm, parts=[part], mesh=s, triangle_part_id=np.zeros(len(s.faces), np.int32))


def _centroid(mask):
    v, u = np.nonzero(mask)
    return u.mean() + 0.5, v.mean() + 0.5  # pixel centres, COCO corner origin


def test_projection_convention_render_and_ray_cast(renderer, planar_rm):
    """A sphere at a known camera-frame point appears at u = fx x / z + cx, v = fy y / z + cy."""
    world_from_camera = look_at(np.array([0.0, 0.0, -0.5]), np.array([0.0, 0.0, 1.0]), np.array([1.0, 0, 0]))
    p_cam = np.array([0.083, -0.061, 1.1])
    centre = world_from_camera[:3, :3] @ p_cam + world_from_camera[:3, 3]
    rm = _sphere_rm(planar_rm, centre, 0.05)
    renderer.set_mesh(rm)
    s = _quiet(_scene(1))
    renderer.set_scene(replace(s, background_rgb=(0.9, 0.9, 0.9)))  # camera looks away from the ground
    raw = renderer.render_raw(world_from_camera)
    _, inst = renderer.depth_and_instance(world_from_camera)
    # the analytic silhouette: pixels whose centre ray passes within the radius of the sphere's centre
    v, u = np.mgrid[0 : K.height, 0 : K.width]
    d = np.stack([(u + 0.5 - K.cx) / K.fx, (v + 0.5 - K.cy) / K.fy, np.ones(u.shape)], -1)
    dist = np.linalg.norm(np.cross(d, p_cam), axis=-1) / np.linalg.norm(d, axis=-1)
    expected = dist < 0.05
    u0, v0 = K.fx * p_cam[0] / p_cam[2] + K.cx, K.fy * p_cam[1] / p_cam[2] + K.cy
    ue, ve = _centroid(expected)
    assert (
        abs(ue - u0) < 0.2 and abs(ve - v0) < 0.2
    )  # a 600-pixel disk's centroid is within a fifth of a pixel
    sky = raw[0, 0]
    rendered = np.abs(raw - sky).sum(-1) > 0.02
    assert expected.sum() > 500
    for mask in (rendered, inst == 0):
        # half a pixel off (the pixel-centre convention) would change a whole rim of ~80 pixels
        assert (mask != expected).sum() <= 6
        u, v = _centroid(mask)
        assert abs(u - ue) < 0.05 and abs(v - ve) < 0.05, (u, v, ue, ve)
    assert set(np.unique(inst)) == {-1, 0}


def test_instance_ids_are_the_part_each_pixel_ray_hits(renderer, tunnel_rm):
    import open3d as o3d

    renderer.set_mesh(tunnel_rm)
    s = _scene(2)
    s = replace(s, distractors=replace(s.distractors, lower_layer=True, spacers=3, formwork_sides=0b0101))
    renderer.set_scene(s)
    T = look_at(np.array([0.1, 0.05, 0.75]), np.array([0.0, 0.0, 0.05]), np.array([1.0, 0, 0]), 0.3)
    depth, inst = renderer.depth_and_instance(T)
    # independent ray cast: every part and surroundings object as its own geometry
    rs = o3d.t.geometry.RaycastingScene()
    ids = []
    for p in tunnel_rm.parts:
        rs.add_triangles(
            o3d.core.Tensor(np.asarray(p.mesh.vertices, np.float32)),
            o3d.core.Tensor(np.asarray(p.mesh.faces, np.uint32)),
        )
        ids.append(p.part_id)
    for obj in build_surroundings(s, tunnel_rm):
        rs.add_triangles(
            o3d.core.Tensor(obj.shape.vertices.astype(np.float32)),
            o3d.core.Tensor(obj.shape.triangles.astype(np.uint32)),
        )
        ids.append(obj.instance_id)
    v, u = np.mgrid[0 : K.height, 0 : K.width]
    d_cam = np.stack([(u + 0.5 - K.cx) / K.fx, (v + 0.5 - K.cy) / K.fy, np.ones_like(u, float)], -1)
    d = d_cam.reshape(-1, 3) @ T[:3, :3].T
    rays = np.concatenate([np.broadcast_to(T[:3, 3], d.shape), d], 1).astype(np.float32)
    hit = rs.cast_rays(o3d.core.Tensor(rays))
    g = hit["geometry_ids"].numpy()
    expected = np.where(g < len(ids), np.array(ids + [-1])[np.minimum(g, len(ids))], -1).reshape(inst.shape)
    found = set(np.unique(inst))
    assert {-2, -3} <= found and len(found - {-1, -2, -3}) >= 10
    agree = inst == expected
    assert agree.mean() > 0.998
    # the few disagreements are silhouette pixels, where the union's re-triangulated edges differ
    edge = (
        (inst != np.roll(inst, 1, 0))
        | (inst != np.roll(inst, -1, 0))
        | (inst != np.roll(inst, 1, 1))
        | (inst != np.roll(inst, -1, 1))
    )
    assert np.all(edge[~agree])
    # depth is z: the independent hit distance along (x, y, 1) directions
    z = hit["t_hit"].numpy().reshape(inst.shape)
    both = np.isfinite(z) & agree
    assert np.allclose(depth[both], z[both], atol=2e-5)
    assert np.all(depth[inst == -1] == 0)


def test_depth_is_metric_z(renderer, planar_rm):
    """Looking straight at the level ground: every ground pixel's depth is the camera's height above it."""
    renderer.set_mesh(planar_rm)
    s = _quiet(_scene(3))
    s = replace(s, ground=replace(s.ground, shape="follow", distance_m=0.3))  # level with the slab
    renderer.set_scene(s)
    T = look_at(np.array([0.05, -0.02, 1.2]), np.array([0.05, -0.02, 0.0]), np.array([1.0, 0, 0]))
    depth, inst = renderer.depth_and_instance(T)
    ground_z = [o for o in build_surroundings(s, planar_rm) if o.name == "ground_plane"][0].shape.vertices[
        0, 2
    ]
    g = inst == -2
    assert g.sum() > 1000
    assert np.allclose(depth[g], 1.2 - ground_z, atol=1e-5)
    # the bars are nearer, and a pixel's depth matches a unit-direction ray cast
    bars = inst >= 0
    assert bars.sum() > 1000 and depth[bars].max() < depth[g].min()
    vv, uu = np.nonzero(bars)
    d = np.stack([(uu + 0.5 - K.cx) / K.fx, (vv + 0.5 - K.cy) / K.fy, np.ones(len(uu))], 1) @ T[:3, :3].T
    unit = d / np.linalg.norm(d, axis=1, keepdims=True)
    t, ids = renderer.cast_rays(np.broadcast_to(T[:3, 3], d.shape), unit)
    assert np.array_equal(ids, inst[bars])
    assert np.allclose(t * (unit @ T[:3, 2]), depth[bars], atol=1e-5)


def test_same_inputs_same_frame_whatever_came_before(renderer, tunnel_rm):
    renderer.set_mesh(tunnel_rm)
    a_scene, b_scene = _scene(4), _scene(5)
    T = look_at(np.array([0.0, 0.1, 0.6]), np.array([0.0, 0.0, 0.05]), np.array([1.0, 0, 0]))
    sensor = replace(OFF, shot_noise=0.01, read_noise=0.004, jpeg_quality=85)
    renderer.set_scene(a_scene)
    first = renderer.render(T, sensor, np.random.default_rng(7))
    renderer.set_scene(b_scene)
    other = renderer.render(T, sensor, np.random.default_rng(7))
    renderer.set_scene(a_scene)
    again = renderer.render(T, sensor, np.random.default_rng(7))
    assert first.rgb.dtype == np.uint8 and first.rgb.shape == (K.height, K.width, 3)
    assert first.depth_m.dtype == np.float32 and first.instance.dtype == np.int32
    assert first.rgb.tobytes() == again.rgb.tobytes()
    assert np.array_equal(first.depth_m, again.depth_m) and np.array_equal(first.instance, again.instance)
    assert not np.array_equal(first.rgb, other.rgb)
    noisy = renderer.render(T, sensor, np.random.default_rng(8))
    assert not np.array_equal(first.rgb, noisy.rgb) and np.array_equal(first.instance, noisy.instance)
    blurred = renderer.render(T, replace(sensor, motion_blur_px=5.0), np.random.default_rng(7))
    sharp_grad = np.abs(np.diff(first.rgb.astype(float), axis=1)).mean()
    assert np.abs(np.diff(blurred.rgb.astype(float), axis=1)).mean() < 0.8 * sharp_grad


def test_user_texture_folder_and_shadow_switch(renderer, tunnel_rm, tmp_path):
    import cv2

    rng = np.random.default_rng(0)
    cv2.imwrite(
        str(tmp_path / "blue_paint_diff_1k.png"),
        np.dstack(
            [
                np.full((64, 64), 200, np.uint8),
                rng.integers(0, 40, (64, 64), np.uint8),
                np.full((64, 64), 20, np.uint8),
            ]
        ),
    )
    cfg = SceneConfig.model_validate(
        {"materials": {"rebar": {"texture_dirs": [str(tmp_path)], "user_texture_probability": 1.0}}}
    )
    s = _quiet(sample_scene(cfg, np.random.default_rng(1)))
    assert s.rebar.source == "user" and s.rebar.user_set.endswith("blue_paint")
    renderer.set_mesh(tunnel_rm)
    renderer.set_scene(s)
    T = look_at(np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.0, 0.05]), np.array([1.0, 0, 0]))
    raw = renderer.render_raw(T)
    _, inst = renderer.depth_and_instance(T)
    bars = raw[inst >= 0]
    assert bars[:, 2].mean() > 1.5 * bars[:, 0].mean()  # the map's blue (BGR file) is on the bars
    lit = replace(s, shadows=True, sun=replace(s.sun, kind="sun", elevation_deg=50.0))
    renderer.set_scene(lit)
    with_shadows = renderer.render_raw(T)
    renderer.set_scene(replace(lit, shadows=False))
    without = renderer.render_raw(T)
    ground = inst == -2
    assert with_shadows[ground].mean() < without[ground].mean()  # the bars' shadows fall on the ground


def test_reuse_over_many_frames(renderer, tunnel_rm):
    renderer.set_mesh(tunnel_rm)
    T = look_at(np.array([0.0, 0.1, 0.6]), np.array([0.0, 0.0, 0.05]), np.array([1.0, 0, 0]))
    frames = []
    for i in range(24):
        if i % 8 == 0:
            renderer.set_scene(_scene(30 + i))
        frames.append(renderer.render(T, OFF, np.random.default_rng(i)))
    assert all(f.rgb.shape == (K.height, K.width, 3) for f in frames)
    assert np.array_equal(frames[16].instance, frames[23].instance)  # one scene: the same geometry
    assert not np.array_equal(frames[0].rgb, frames[8].rgb)  # a new scene: new looks


def test_one_open_renderer_per_process(renderer):
    with pytest.raises(RuntimeError, match="already open"):
        Renderer(K, RenderConfig())
