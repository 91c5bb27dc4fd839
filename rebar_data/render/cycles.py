"""Blender Cycles renderer: the same meshes, scenes, cameras and labels as the Open3D renderer, another image.

A detector trained on Open3D's frames is scored on frames from a path tracer it never saw: only the RGB
image changes. :class:`CyclesRenderer` has :class:`rebar_data.render.renderer.Renderer`'s interface
(``set_mesh``, ``set_scene``, ``render``, ``cast_rays``, ``close``, a context manager), so the dataset
build uses either. Depth, instance ids and :meth:`cast_rays` (what the labels are made from) come from the
same ray cast as the Open3D renderer's (:class:`rebar_data.render.raycast.SceneRaycast`), against the same
surroundings (:func:`rebar_data.scene.surroundings.build_surroundings`): labels are identical whichever
renderer drew the image.

The image: Cycles path tracing on the CPU (``render.cycles``: samples, adaptive sampling, bounces,
OpenImageDenoise) of the scene's look (:mod:`rebar_data.render.cycles_looks`): sun and Nishita sky at
noon or dusk or an overcast sky, the scene's lamps as area, spot and point lights, procedural steel,
rust, mill scale, epoxy, concrete, soil, wood and gravel. The linear result goes through the same camera
model as the Open3D path (:func:`rebar_data.render.sensor.apply_sensor`: blur, vignetting, exposure,
noise, tone curve, JPEG).

Blender works in a "render frame": the world turned so that the mat's outward normal is Blender's up
(+z) and the mat's centre is the origin, so the sky stands over the mat whichever way the mesh faces.
The pinhole camera is matched exactly: focal length from ``fx`` on a horizontal sensor fit, pixel aspect
``fx / fy``, and the principal point as lens shift; Cycles' pixel ``(i, j)`` covers ``[i, i + 1]`` in
COCO's corner-origin coordinates, as the labels assume (tested to a tenth of a pixel).

``bpy`` (Blender as a Python module, the optional extra ``cycles``) holds one global scene per process, so
there is one open ``CyclesRenderer`` per process.
"""

from __future__ import annotations

import os
import shutil
import sys
from contextlib import contextmanager

import numpy as np

from rebar_data.camera import Intrinsics
from rebar_data.config import ConfigError
from rebar_data.geometry.build import RebarMesh
from rebar_data.outputs import private_temp_dir
from rebar_data.render import cycles_looks as looks
from rebar_data.render.raycast import Frame, SceneRaycast
from rebar_data.scene.config import RenderConfig
from rebar_data.scene.lighting import direction_in_frame, kelvin_to_rgb
from rebar_data.scene.mat_surface import MatSurface
from rebar_data.scene.sample import SceneSample, SensorSample
from rebar_data.scene.surroundings import SceneObject, build_surroundings
from rebar_data.scene.textures import bar_tints
from rebar_data.timing import StageTimer

__all__ = ["CyclesRenderer", "blender_version", "require_bpy"]

CYCLES_INSTALL_HINT = "pip install -e '.[cycles]' (or make crossval, which installs it)"
TARGET_IRRADIANCE = 3.0  # the mat's centre gets this much light (Blender units): a white surface near 1.0
CYCLES_NEAR_M, CYCLES_FAR_M = 0.01, 200.0
CAMERA_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # Blender's camera looks down -z with +y up
_OPEN: list[CyclesRenderer] = []


def require_bpy():
    """The ``bpy`` module, or a ConfigError saying how to install it."""
    try:
        import bpy
    except ImportError as e:
        raise ConfigError(
            f"render.engine: cycles needs Blender's bpy module, which is not installed ({e}); {CYCLES_INSTALL_HINT}"
        ) from None
    return bpy


def blender_version() -> str:
    """Blender's version string (such as ``4.2.0``)."""
    return require_bpy().app.version_string


@contextmanager
def _quiet():
    """Silence Blender's progress lines, printed by C code to stdout (the build's stdout is for its path)."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def render_from_world(n: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Rigid transform taking the mat's centre to the origin and its outward normal ``n`` to +z."""
    z = n / np.linalg.norm(n)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z])
    T[:3, 3] = -T[:3, :3] @ centre
    return T


def camera_settings(k: Intrinsics) -> dict[str, float]:
    """Blender camera and render settings that reproduce pinhole intrinsics ``k`` (COCO corner origin).

    With a horizontal sensor fit the focal length is ``fx`` pixels of the image width; a pixel aspect of
    ``fx / fy`` makes pixels ``fx / fy`` times as tall as wide at the same focal length; the lens shift is
    in units of the image width, positive towards +x (right) and +y (up).
    """
    sensor_mm = 36.0
    ycor = k.fx / k.fy  # a pixel's height over its width
    return {
        "sensor_width": sensor_mm,
        "lens": k.fx * sensor_mm / k.width,
        "shift_x": (k.width / 2.0 - k.cx) / k.width,
        "shift_y": (k.cy - k.height / 2.0) * ycor / k.width,
        "pixel_aspect_x": max(1.0, 1.0 / ycor),
        "pixel_aspect_y": max(1.0, ycor),
    }


class CyclesRenderer(SceneRaycast):
    """Renders frames of one rebar mesh with Blender Cycles; reuse it for every frame of a worker."""

    def __init__(self, intrinsics: Intrinsics, cfg: RenderConfig | None = None):
        if _OPEN:
            raise RuntimeError("a CyclesRenderer is already open in this process; close() it first")
        self._bpy = bpy = require_bpy()
        self.intrinsics = intrinsics
        self.cfg = cfg if cfg is not None else RenderConfig()
        self._rm: RebarMesh | None = None
        self._surf: MatSurface | None = None
        self._scene_sample: SceneSample | None = None
        self.look: looks.CyclesLook | None = None
        self._render_from_world = np.eye(4)
        self._mesh_objects: list = []  # the rebar: kept across scenes
        self._bar_vertex_counts: list[int] = []
        self._scene_objects: list = []  # surroundings and lights: replaced by every scene
        self._tmp = str(private_temp_dir("rebar-cycles-"))  # a pool worker ended by terminate() leaves it
        self._init_raycast(intrinsics)
        self.timer = StageTimer()  # seconds per stage of render(): cycles, rays, sensor
        with _quiet():
            bpy.ops.wm.read_factory_settings(use_empty=True)
        self._setup_render(bpy.context.scene)
        cam = bpy.data.cameras.new("camera")
        self._camera = bpy.data.objects.new("camera", cam)
        bpy.context.scene.collection.objects.link(self._camera)
        bpy.context.scene.camera = self._camera
        for key, value in camera_settings(intrinsics).items():
            target = bpy.context.scene.render if key.startswith("pixel_aspect") else cam
            setattr(target, key, value)
        cam.sensor_fit = "HORIZONTAL"
        cam.clip_start, cam.clip_end = CYCLES_NEAR_M, CYCLES_FAR_M
        _OPEN.append(self)

    def _setup_render(self, sc) -> None:
        c = self.cfg.cycles
        k = self.intrinsics
        r = sc.render
        r.engine = "CYCLES"
        r.resolution_x, r.resolution_y, r.resolution_percentage = k.width, k.height, 100
        r.threads_mode = "FIXED" if c.threads > 0 else "AUTO"
        if c.threads > 0:
            r.threads = c.threads
        # no persistent data: with it, a scene rendered after another one came out different (stale state)
        r.use_persistent_data = False
        r.image_settings.file_format = "OPEN_EXR"
        r.image_settings.color_depth = "32"
        r.image_settings.exr_codec = "NONE"
        r.filepath = os.path.join(self._tmp, "frame.exr")
        sc.view_settings.view_transform = "Standard"  # the EXR holds scene-linear light either way
        cy = sc.cycles
        cy.device = "CPU"
        cy.samples = c.samples
        cy.use_adaptive_sampling = True
        cy.adaptive_threshold = c.adaptive_threshold
        cy.max_bounces = c.max_bounces
        cy.diffuse_bounces = cy.glossy_bounces = c.max_bounces
        cy.transmission_bounces = cy.volume_bounces = 0
        cy.transparent_max_bounces = 2
        cy.caustics_reflective = cy.caustics_refractive = False
        cy.sample_clamp_indirect = 10.0  # no fireflies from glossy steel at a few dozen samples
        cy.use_denoising = c.denoise
        cy.denoiser = "OPENIMAGEDENOISE"
        cy.denoising_input_passes = "RGB_ALBEDO_NORMAL"
        cy.use_animated_seed = False
        cy.use_light_tree = False  # a few lights: sampling them all is about 8% faster than the tree

    # --- set-up ---------------------------------------------------------------------------------------

    def set_mesh(self, rm: RebarMesh) -> None:
        """Use ``rm`` for the rebar (once per mesh); call :meth:`set_scene` before rendering."""
        self._remove(self._scene_objects)
        self._remove(self._mesh_objects)
        self._rm = rm
        self._surf = MatSurface.of(rm)
        self._scene_sample = None
        self._raycast = None
        centre, _, _, n = (x[0] for x in self._surf.frame(self._surf.centre()))
        self._render_from_world = render_from_world(n, centre)
        self._mesh_objects = self._rebar_objects(rm)

    def _rebar_objects(self, rm: RebarMesh) -> list:
        """One Blender object for the bars (with a tint and a random number per bar as attributes), one
        for the tie wire."""
        out = []
        for kind in ("bar", "tie_wire"):
            idx = [i for i, p in enumerate(rm.parts) if p.kind == kind]
            if not idx:
                continue
            meshes = [rm.parts[i].mesh for i in idx]
            verts = np.concatenate([np.asarray(m.vertices) for m in meshes])
            offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
            tris = np.concatenate([np.asarray(m.faces) + o for m, o in zip(meshes, offsets, strict=True)])
            out.append(self._object(f"rebar_{kind}", verts, tris, smooth_deg=35.0))
            if kind == "bar":  # the bars' attributes are set per scene (their tints change)
                self._bar_vertex_counts = [len(m.vertices) for m in meshes]
        return out

    def _object(self, name: str, verts, tris, *, uv_m=None, smooth_deg: float | None = None):
        bpy = self._bpy
        me = bpy.data.meshes.new(name)
        tris = np.asarray(tris, np.int32)
        me.vertices.add(len(verts))
        me.vertices.foreach_set("co", np.asarray(verts, np.float32).ravel())
        me.loops.add(3 * len(tris))
        me.loops.foreach_set("vertex_index", tris.ravel())
        me.polygons.add(len(tris))
        me.polygons.foreach_set("loop_start", np.arange(0, 3 * len(tris), 3, dtype=np.int32))
        if uv_m is not None:
            layer = me.uv_layers.new(name="UVMap")
            layer.data.foreach_set("uv", np.asarray(uv_m, np.float32).ravel())
        me.update()
        if smooth_deg is not None:
            me.shade_smooth()
            me.set_sharp_from_angle(angle=float(np.radians(smooth_deg)))
        obj = bpy.data.objects.new(name, me)
        obj.matrix_world = _matrix(self._render_from_world)
        bpy.context.scene.collection.objects.link(obj)
        return obj

    def _remove(self, objects: list) -> None:
        bpy = self._bpy
        for obj in objects:
            data = obj.data
            bpy.data.objects.remove(obj)
            if isinstance(data, bpy.types.Mesh):
                bpy.data.meshes.remove(data)
            elif isinstance(data, bpy.types.Light):
                bpy.data.lights.remove(data)
        objects.clear()

    def _clear_scene(self) -> None:
        bpy = self._bpy
        self._remove(self._scene_objects)
        for mat in list(bpy.data.materials):
            bpy.data.materials.remove(mat)
        for w in list(bpy.data.worlds):
            bpy.data.worlds.remove(w)

    def set_scene(self, scene: SceneSample) -> None:
        """Lights, sky, materials, surroundings and distractors of ``scene`` (after :meth:`set_mesh`)."""
        if self._rm is None:
            raise RuntimeError("set_mesh(rm) must come before set_scene(scene)")
        bpy = self._bpy
        rm, surf = self._rm, self._surf
        self._clear_scene()
        self._scene_sample = scene
        self.look = look = looks.draw_look(scene)
        objects = build_surroundings(scene, rm, surf)
        mats = {
            "rebar": looks.steel_material(bpy, look),
            "tie_wire": looks.tie_wire_material(bpy, look),
            "ground": looks.ground_material(bpy, look, look.ground, "ground"),
            "concrete": looks.ground_material(bpy, look, "concrete", "concrete"),
            "plywood": looks.ground_material(bpy, look, "wood", "plywood"),
        }
        for obj in self._mesh_objects:
            obj.data.materials.clear()
            obj.data.materials.append(mats["rebar" if obj.name == "rebar_bar" else "tie_wire"])
            if obj.name == "rebar_bar":
                self._bar_attributes(obj, scene)
        for so in objects:
            self._scene_objects.append(self._surroundings_object(so, mats[so.material]))
        self._lights(scene, look)
        self._build_raycast(objects)

    def _bar_attributes(self, obj, scene: SceneSample) -> None:
        """Per-bar tint (as the Open3D renderer's: darker bars a little warmer) and a random number."""
        rng = np.random.default_rng(scene.rebar.tint_seed)
        counts = self._bar_vertex_counts
        rgb = bar_tints(scene.rebar, len(counts), rng)
        rand = rng.uniform(0.0, 1.0, len(counts))
        _point_attribute(obj.data, "bar_tint", np.repeat(rgb, counts, axis=0))
        _point_attribute(obj.data, "bar_random", np.repeat(rand, counts))

    def _surroundings_object(self, so: SceneObject, mat):
        s = so.shape
        smooth = {"tie_wire": 65.0, "rebar": 50.0, "concrete": 35.0}.get(so.material)
        obj = self._object(so.name, s.vertices, s.triangles, uv_m=s.corner_uv_m, smooth_deg=smooth)
        if so.material == "rebar":  # the lower bar layer: the bars' material, one tint
            _point_attribute(obj.data, "bar_tint", np.ones((len(s.vertices), 3)))
            _point_attribute(obj.data, "bar_random", np.full(len(s.vertices), 0.5))
        obj.data.materials.append(mat)
        return obj

    def _lights(self, scene: SceneSample, look: looks.CyclesLook) -> None:
        """Sun, sky and lamps, all scaled so the mat's centre gets TARGET_IRRADIANCE (as auto-exposure)."""
        bpy = self._bpy
        surf = self._surf
        centre, t_a, t_b, n = (x[0] for x in surf.frame(surf.centre()))
        R = self._render_from_world[:3, :3]
        to_sun = direction_in_frame(look.sun_azimuth_deg, look.sun_elevation_deg, t_a, t_b, n)
        sun_on_mat = look.sun_lux * max(float(np.dot(to_sun, n)), 0.0)
        lamps = []
        for lamp in scene.lamps:
            if lamp.kind == "none":
                continue
            to_lamp = direction_in_frame(lamp.azimuth_deg, lamp.elevation_deg, t_a, t_b, n)
            lamps.append((lamp, to_lamp, lamp.illuminance_lux * max(float(np.dot(to_lamp, n)), 0.0)))
        total = sun_on_mat + look.sky_lux + sum(x[2] for x in lamps)
        scale = TARGET_IRRADIANCE / max(total, 1e-6)
        sun_dir = R @ to_sun
        if look.sun_lux > 0:
            self._light(
                "sun",
                "SUN",
                colour=kelvin_to_rgb(look.sun_temperature_k),
                energy=look.sun_lux * scale,
                position=sun_dir * 50.0,
                facing=-sun_dir,
                angle=float(np.radians(look.sun_angle_deg)),
            )
        strength = look.sky_lux * scale / looks.sky_irradiance(look)
        bpy.context.scene.world = looks.world(bpy, look, strength, sun_dir)
        # Blender's lights, measured on a white plane: a point or spot light of power P gives P / (4 pi d^2)
        # at distance d to a surface facing it, an area light P / (pi d^2), a sun of strength S gives S
        for i, (lamp, to_lamp, _) in enumerate(lamps):
            d = lamp.distance_m
            pos = R @ (d * to_lamp)
            e = lamp.illuminance_lux * scale  # on a surface facing the lamp, at the mat's centre
            colour = kelvin_to_rgb(lamp.temperature_k)
            if lamp.kind == "area":
                kind, energy, shape = "AREA", e * np.pi * d**2, {"size": max(lamp.size_m, 0.05)}
            else:
                kind, energy, shape = lamp.kind.upper(), e * 4.0 * np.pi * d**2, {"radius": 0.05}
                if lamp.kind == "spot":
                    shape["spot_size"] = float(np.radians(lamp.cone_deg))
            self._light(
                f"lamp{i}", kind, colour=colour, energy=energy, position=pos, facing=-pos / d, **shape
            )

    def _light(
        self,
        name,
        kind,
        *,
        colour,
        energy,
        position,
        facing,
        angle=None,
        size=None,
        spot_size=None,
        radius=None,
    ) -> None:
        bpy = self._bpy
        ld = bpy.data.lights.new(name, kind)
        ld.color = tuple(float(c) for c in colour)
        ld.energy = float(energy)
        if angle is not None:
            ld.angle = angle
        if size is not None:
            ld.size = float(size)
        if spot_size is not None:
            ld.spot_size = spot_size
            ld.spot_blend = 0.3
        if radius is not None:
            ld.shadow_soft_size = radius
        obj = bpy.data.objects.new(name, ld)
        T = np.eye(4)
        T[:3, :3] = _frame_with_z(-np.asarray(facing, float))  # lights shine down their local -z
        T[:3, 3] = position
        obj.matrix_world = _matrix(T)
        bpy.context.scene.collection.objects.link(obj)
        self._scene_objects.append(obj)

    # --- per frame ------------------------------------------------------------------------------------

    def render_raw(self, world_from_camera: np.ndarray, *, seed: int = 0) -> np.ndarray:
        """The rendered image before sensor effects: (H, W, 3) float32, scene-linear light."""
        if self._scene_sample is None:
            raise RuntimeError("set_mesh(rm) and set_scene(scene) must come before render")
        bpy = self._bpy
        sc = bpy.context.scene
        render_from_camera = (
            self._render_from_world @ np.asarray(world_from_camera, float) @ CAMERA_FROM_OPENCV
        )
        self._camera.matrix_world = _matrix(render_from_camera)
        sc.cycles.seed = int(seed)
        with _quiet():
            bpy.ops.render.render(write_still=True)
        img = bpy.data.images.load(sc.render.filepath)
        try:
            k = self.intrinsics
            px = np.empty(k.width * k.height * 4, np.float32)
            img.pixels.foreach_get(px)
        finally:
            bpy.data.images.remove(img)
        return np.ascontiguousarray(px.reshape(k.height, k.width, 4)[::-1, :, :3])  # rows bottom-up

    def render(self, world_from_camera: np.ndarray, sensor: SensorSample, rng: np.random.Generator) -> Frame:
        """RGB (after ``sensor`` effects, noise from ``rng``), depth and instance ids of one camera pose."""
        with self.timer("cycles"):
            raw = self.render_raw(world_from_camera, seed=int(rng.integers(2**31 - 1)))
        return self._finish_frame(raw, world_from_camera, sensor, rng)

    def close(self) -> None:
        """Drop this renderer's Blender data and temporary files."""
        if self in _OPEN:
            self._clear_scene()
            self._remove(self._mesh_objects)
            self._raycast = None
            shutil.rmtree(self._tmp, ignore_errors=True)
            _OPEN.remove(self)

    def __enter__(self) -> CyclesRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _point_attribute(mesh, name: str, values: np.ndarray) -> None:
    values = np.asarray(values, np.float32)
    if name in mesh.attributes:
        mesh.attributes.remove(mesh.attributes[name])
    if values.ndim == 2:
        attr = mesh.attributes.new(name, "FLOAT_COLOR", "POINT")
        rgba = np.concatenate([values, np.ones((len(values), 1), np.float32)], axis=1)
        attr.data.foreach_set("color", rgba.ravel())
    else:
        attr = mesh.attributes.new(name, "FLOAT", "POINT")
        attr.data.foreach_set("value", values)


def _frame_with_z(z: np.ndarray) -> np.ndarray:
    """A rotation whose third column is the unit vector ``z``."""
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _matrix(T: np.ndarray):
    from mathutils import Matrix

    return Matrix([[float(v) for v in row] for row in np.asarray(T)])
