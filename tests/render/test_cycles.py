"""Cycles renderer: the pinhole camera is reproduced to a fraction of a pixel, labels, depth and instance
ids equal the Open3D renderer's, the look follows the scene's seed. Skipped without Blender's bpy."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh

pytest.importorskip("bpy", reason="Blender's bpy module is not installed (pip install -e '.[cycles]')")

from rebar_data.camera import Intrinsics  # noqa: E402
from rebar_data.geometry.solids import Part  # noqa: E402
from rebar_data.labels.keypoints import CrossingParts, label_frame  # noqa: E402
from rebar_data.render.cycles import CyclesRenderer, camera_settings  # noqa: E402
from rebar_data.render.cycles_looks import draw_look  # noqa: E402
from rebar_data.scene.cameras import look_at  # noqa: E402
from rebar_data.scene.config import CyclesConfig, RenderConfig, SceneConfig  # noqa: E402
from rebar_data.scene.sample import sample_scene, sample_sensor  # noqa: E402

FAST = RenderConfig(engine="cycles", cycles=CyclesConfig(samples=8, denoise=False, threads=2))


def _scene(seed: int):
    return sample_scene(SceneConfig(), np.random.default_rng(seed))


def _spheres_rm(base_rm, centres, radius):
    """A mesh whose parts are small spheres (as tie wire: no bar attributes needed)."""
    parts, meshes = [], []
    for i, c in enumerate(centres):
        s = trimesh.creation.icosphere(subdivisions=4, radius=radius)
        s.apply_translation(c)
        parts.append(Part(i, "tie_wire", -1, -1, s))
        meshes.append(s)
    merged = trimesh.util.concatenate(meshes)
    part_id = np.repeat(np.arange(len(meshes), dtype=np.int32), [len(m.faces) for m in meshes])
    return replace(base_rm, parts=parts, mesh=merged, triangle_part_id=part_id)


@pytest.mark.parametrize(
    "k",
    [
        Intrinsics(160, 120, 131.25, 131.25, 80.0, 60.0),  # Kinect v1 at a quarter of its size
        Intrinsics(200, 150, 180.0, 165.0, 93.3, 81.7),  # fx != fy, principal point off centre
    ],
)
def test_spheres_land_where_the_pinhole_projects_them(planar_rm, k):
    """Bright spheres at known camera-frame points: their centroids are at u = fx x/z + cx, v = fy y/z + cy
    (COCO corner origin) within a tenth of a pixel."""
    import bpy

    world_from_camera = look_at(
        np.array([0.05, -0.02, 0.9]), np.array([0.0, 0.0, 0.0]), np.array([1.0, 0, 0])
    )
    z = 0.6
    p_cam = np.array([[0.0, 0.0, z], [0.2, 0.13, z], [-0.21, 0.1, z], [0.18, -0.14, z], [-0.2, -0.15, 0.7]])
    p_cam[:, :2] *= np.array([k.width / 2 / k.fx, k.height / 2 / k.fy]) / 0.4  # spread over the frame
    centres = p_cam @ world_from_camera[:3, :3].T + world_from_camera[:3, 3]
    rm = _spheres_rm(planar_rm, centres, 0.012)  # about 3 px across
    cfg = RenderConfig(engine="cycles", cycles=CyclesConfig(samples=32, denoise=False, threads=2))
    with CyclesRenderer(k, cfg) as r:
        r.set_mesh(rm)
        r.set_scene(_scene(1))
        for obj in bpy.context.scene.objects:  # spheres only, glowing on black
            obj.hide_render = obj.name != "rebar_tie_wire" and obj.type != "CAMERA"
        glow = bpy.data.materials.new("glow")
        glow.use_nodes = True
        nodes = glow.node_tree.nodes
        nodes.clear()
        em = nodes.new("ShaderNodeEmission")
        out = nodes.new("ShaderNodeOutputMaterial")
        glow.node_tree.links.new(em.outputs[0], out.inputs["Surface"])
        sphere = bpy.data.objects["rebar_tie_wire"]
        sphere.data.materials.clear()
        sphere.data.materials.append(glow)
        bpy.context.scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
        raw = r.render_raw(world_from_camera).sum(-1)
    import cv2

    n, labels = cv2.connectedComponents((raw > 0.02).astype(np.uint8))
    assert n - 1 == len(p_cam)
    found = []
    for i in range(1, n):
        v, u = np.nonzero(labels == i)
        w = raw[v, u]
        found.append(((u + 0.5) * w).sum() / w.sum())
        found[-1] = (found[-1], ((v + 0.5) * w).sum() / w.sum())
    expected = np.stack([k.fx * p_cam[:, 0] / p_cam[:, 2] + k.cx, k.fy * p_cam[:, 1] / p_cam[:, 2] + k.cy], 1)
    errors = []
    for u, v in found:
        err = np.linalg.norm(expected - [u, v], axis=1).min()
        errors.append(err)
    print("centroid errors px", np.round(errors, 3))
    assert max(errors) < 0.1, errors


def test_camera_settings_keep_the_pinhole():
    s = camera_settings(Intrinsics(640, 480, 525.0, 525.0, 320.0, 240.0))
    assert s["shift_x"] == 0.0 and s["shift_y"] == 0.0 and s["pixel_aspect_x"] == s["pixel_aspect_y"] == 1.0
    assert s["lens"] == pytest.approx(525.0 * 36.0 / 640.0)


def test_labels_depth_and_instances_equal_the_open3d_renderer(tunnel_rm):
    """The same pose and scene labelled through either renderer: identical labels, depth and instance ids,
    and a plausible image (neither black nor blown out)."""
    from rebar_data.render.renderer import Renderer

    k = Intrinsics(160, 120, 131.25, 131.25, 80.0, 60.0)
    scene = _scene(5)
    scene = replace(scene, distractors=replace(scene.distractors, lower_layer=True, spacers=3))
    T = look_at(np.array([0.08, 0.05, 0.6]), np.array([0.0, 0.0, 0.1]), np.array([1.0, 0, 0]), 0.3)
    parts = CrossingParts.of(tunnel_rm)
    out = {}
    for name, cls, cfg in (
        ("open3d", Renderer, RenderConfig(texture_size_px=256)),
        ("cycles", CyclesRenderer, FAST),
    ):
        with cls(k, cfg) as r:
            r.set_mesh(tunnel_rm)
            r.set_scene(scene)
            rng = np.random.default_rng(3)
            frame = r.render(T, sample_sensor(SceneConfig(), rng), rng)
            out[name] = (frame, label_frame(tunnel_rm, parts, T, k, r.cast_rays))
    (f_o, l_o), (f_c, l_c) = out["open3d"], out["cycles"]
    assert (l_c.visibility == 2).sum() > 5
    for field in ("u", "v", "visibility", "depth_m", "box_size_px", "hit_instance", "point_world"):
        np.testing.assert_array_equal(getattr(l_c, field), getattr(l_o, field), err_msg=field)
    np.testing.assert_array_equal(f_c.depth_m, f_o.depth_m)
    np.testing.assert_array_equal(f_c.instance, f_o.instance)
    assert f_c.rgb.shape == (k.height, k.width, 3) and f_c.rgb.dtype == np.uint8
    assert 30 < f_c.rgb.mean() < 220 and f_c.rgb.std() > 10


def test_look_follows_the_scene_sample():
    a, b = draw_look(_scene(11)), draw_look(_scene(11))
    assert a == b
    looks = {draw_look(_scene(s)).finish for s in range(40)} | {draw_look(_scene(s)).sky for s in range(40)}
    assert {"bright", "rust", "mill_scale", "epoxy", "noon", "dusk", "overcast"} <= looks


def test_a_scene_renders_the_same_after_another_scene(tunnel_rm):
    """Blender keeps no state from one scene into the next: scene A, then B, then A again gives A's image."""
    k = Intrinsics(64, 48, 52.5, 52.5, 32.0, 24.0)
    T = look_at(np.array([0.05, 0.02, 0.6]), np.array([0.0, 0.0, 0.1]), np.array([1.0, 0, 0]))
    cfg = RenderConfig(engine="cycles", cycles=CyclesConfig(samples=4, denoise=False, threads=2))
    with CyclesRenderer(k, cfg) as r:
        r.set_mesh(tunnel_rm)
        images = []
        for seed in (21, 22, 21):
            r.set_scene(_scene(seed))
            images.append(r.render_raw(T, seed=7))
    np.testing.assert_array_equal(images[0], images[2])
    assert np.abs(images[0] - images[1]).max() > 0.01
