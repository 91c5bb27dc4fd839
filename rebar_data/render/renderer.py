"""Open3D offscreen renderer (Filament through EGL) with exact depth and instance ids from a ray cast.

One :class:`Renderer` per process: it creates Open3D's ``OffscreenRenderer`` once and reuses it for every
mesh, scene and frame, so memory stays flat over thousands of frames. Per frame it renders the RGB image
(linear, no Filament post-processing unless asked), casts one ray through every pixel centre against the
same triangles (``open3d.t.geometry.RaycastingScene``, through :class:`rebar_data.render.raycast.SceneRaycast`,
which the Cycles renderer shares) for metric depth and instance ids, and applies the frame's sensor effects.

Instance ids: ``>= 0`` the part of ``rm.parts`` (primitive ids of the merged mesh mapped through
``rm.triangle_part_id``), ``-1`` nothing, ``-2`` ground, ``-3`` distractors. Depth is the ray cast's
(exact): z in the camera frame, 0 where nothing was hit.

Filament's image-based light cannot be turned from Python and has +y up, so the renderer draws in a
"render frame": the world turned so that the mat's outward normal is +y and the environment's rotation
applied, with the mat's centre at the origin. Cameras and lights are moved into that frame too; nothing
visible changes except which way the environment faces.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from rebar_data.camera import Intrinsics
from rebar_data.geometry.build import RebarMesh
from rebar_data.outputs import private_temp_dir
from rebar_data.render.raycast import Frame, SceneRaycast
from rebar_data.render.uv import bar_corner_uv_m
from rebar_data.scene.config import RenderConfig
from rebar_data.scene.lighting import light_specs
from rebar_data.scene.mat_surface import MatSurface
from rebar_data.scene.sample import SceneSample, SensorSample
from rebar_data.scene.surroundings import SceneObject, build_surroundings
from rebar_data.scene.texture_folders import load_texture_set
from rebar_data.scene.textures import (
    TextureCache,
    bar_tints,
    ground_maps,
    rebar_fields,
    rebar_maps,
    rebar_tint,
)
from rebar_data.timing import StageTimer

__all__ = ["Frame", "RenderConfig", "Renderer"]

NEAR_M, FAR_M = 0.05, 10.0  # clipping planes: cameras work at 0.3-1 m and see the ground within 7 m


_OFFSCREEN = None  # (width, height, OffscreenRenderer): one per process, reused
_OPEN: list[Renderer] = []
_SHADOWS_WARM = False  # Filament's first frame with shadow maps differs from every later one


def _offscreen(width: int, height: int):
    """The process's OffscreenRenderer of this size (Filament allows one live renderer per process)."""
    global _OFFSCREEN, _SHADOWS_WARM
    if "EGL_PLATFORM" not in os.environ and not Path("/dev/nvidiactl").exists():
        os.environ["EGL_PLATFORM"] = "surfaceless"  # Mesa's llvmpipe, no display; a GPU's EGL needs none
    from open3d.visualization import rendering

    if _OFFSCREEN is not None and _OFFSCREEN[:2] == (width, height):
        return _OFFSCREEN[2]
    if _OFFSCREEN is not None:
        _OFFSCREEN[2].scene.clear_geometry()
        _OFFSCREEN = None
        import gc

        gc.collect()
    with _quiet_start():
        _OFFSCREEN = (width, height, rendering.OffscreenRenderer(width, height))
    _SHADOWS_WARM = False
    return _OFFSCREEN[2]


@contextmanager
def _quiet_start() -> Iterator[None]:
    """Keep the renderer's start-up text out of the user's output: Filament's and EGL's lines on stdout,
    Open3D's info line, and Mesa's ``error: XDG_RUNTIME_DIR is invalid or not set`` on stderr (answered by
    a private folder for the start when the variable is unset). File descriptors 1 and 2 go to a temporary
    file for the block only; what was captured is shown on stderr if the start fails."""
    import open3d as o3d

    level = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    runtime_dir = None
    if not os.environ.get("XDG_RUNTIME_DIR"):
        runtime_dir = str(private_temp_dir("rebar-runtime-"))  # mode 0700, as the variable requires
        os.environ["XDG_RUNTIME_DIR"] = runtime_dir
    try:
        with _fds_captured() as captured:
            try:
                yield
            except BaseException:
                sys.stderr.write(captured())
                raise
    finally:
        o3d.utility.set_verbosity_level(level)
        if runtime_dir is not None:
            os.environ.pop("XDG_RUNTIME_DIR", None)
            shutil.rmtree(runtime_dir, ignore_errors=True)


@contextmanager
def _fds_captured() -> Iterator:
    """Native writes to fds 1 and 2 go to a temporary file for the block; yields a function that reads it
    (after the block's fds are back). Without fds 1 and 2 (a daemon) the block runs as it is."""
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        saved = (os.dup(1), os.dup(2))
    except OSError:
        yield lambda: ""
        return
    with tempfile.TemporaryFile() as log:
        os.dup2(log.fileno(), 1)
        os.dup2(log.fileno(), 2)

        def captured() -> str:
            _restore(saved)
            log.seek(0)
            return log.read().decode(errors="replace")

        try:
            yield captured
        finally:
            _restore(saved)
            for fd in saved:
                os.close(fd)


def _restore(saved: tuple[int, int]) -> None:
    """Flush C's stdio buffers into the capture, then point fds 1 and 2 back (idempotent)."""
    try:
        import ctypes

        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):
        pass
    os.dup2(saved[0], 1)
    os.dup2(saved[1], 2)


def _resources() -> Path:
    import open3d

    return Path(open3d.__file__).parent / "resources"


def _render_from_world(normal: np.ndarray, centre: np.ndarray, rotation_deg: float) -> np.ndarray:
    """Rigid transform taking the mat's centre to the origin and its outward normal to +y, then turning
    about +y by ``rotation_deg``."""
    y = normal / np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(y[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(y, helper)
    x /= np.linalg.norm(x)
    z = np.cross(x, y)
    align = np.stack([x, y, z])  # rows: world directions that become render x, y, z
    a = np.radians(rotation_deg)
    turn = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    T = np.eye(4)
    T[:3, :3] = turn @ align
    T[:3, 3] = -T[:3, :3] @ centre
    return T


class Renderer(SceneRaycast):
    """Renders frames of one rebar mesh in a sampled scene; reuse it for every frame of a worker."""

    def __init__(self, intrinsics: Intrinsics, cfg: RenderConfig | None = None):
        cfg = cfg if cfg is not None else RenderConfig()
        if _OPEN:
            raise RuntimeError("a Renderer is already open in this process; close() it before making another")
        from open3d.visualization import rendering

        self._rendering = rendering
        self.intrinsics = intrinsics
        self.cfg = cfg
        self._o3d = _offscreen(intrinsics.width, intrinsics.height)
        self._o3d.scene.clear_geometry()
        self._o3d.scene.scene.enable_sun_light(False)
        view = self._o3d.scene.view
        view.set_post_processing(cfg.post_processing)
        self._textures = TextureCache(cfg.cache_dir)
        self._rebar_maps: OrderedDict = OrderedDict()
        self._rm: RebarMesh | None = None
        self._surf: MatSurface | None = None
        self._scene: SceneSample | None = None
        self._geometry: list[str] = []  # names in the Open3D scene
        self._lights: list[str] = []
        self._ibl: str | None = None
        self._init_raycast(intrinsics)
        self._render_from_world = np.eye(4)
        self._shadows_on = False
        self.timer = StageTimer()  # seconds per stage of render(): filament, rays, sensor
        _OPEN.append(self)

    # --- set-up ---------------------------------------------------------------------------------------

    def set_mesh(self, rm: RebarMesh) -> None:
        """Use ``rm`` for the rebar (once per mesh); call :meth:`set_scene` before rendering."""
        self._rm = rm
        self._surf = MatSurface.of(rm)
        self._rebar_meshes = self._rebar_geometry(rm)
        self._scene = None
        self._clear()

    def _rebar_geometry(self, rm: RebarMesh):
        """Open3D meshes of the bars (with texture coordinates in metres) and of the tie wire."""
        import open3d as o3d

        out = {}
        for kind in ("bar", "tie_wire"):
            idx = [i for i, p in enumerate(rm.parts) if p.kind == kind]
            if not idx:
                continue
            verts, tris, uvs, offset = [], [], [], 0
            for i in idx:
                m = rm.parts[i].mesh
                verts.append(np.asarray(m.vertices))
                tris.append(np.asarray(m.faces) + offset)
                offset += len(m.vertices)
                uvs.append(bar_corner_uv_m(rm, i) if kind == "bar" else np.zeros((len(m.faces), 3, 2)))
            mesh = o3d.geometry.TriangleMesh(
                o3d.utility.Vector3dVector(np.concatenate(verts)),
                o3d.utility.Vector3iVector(np.concatenate(tris).astype(np.int32)),
            )
            mesh.compute_vertex_normals()
            out[kind] = (mesh, np.concatenate(uvs).reshape(-1, 2))
        return out

    def _clear(self) -> None:
        scene = self._o3d.scene
        for name in self._geometry:
            scene.remove_geometry(name)
        for name in self._lights:
            scene.scene.remove_light(name)
        self._geometry, self._lights = [], []

    def set_scene(self, scene: SceneSample) -> None:
        """Lights, materials, surroundings and distractors of ``scene`` (after :meth:`set_mesh`)."""
        if self._rm is None:
            raise RuntimeError("set_mesh(rm) must come before set_scene(scene)")
        import open3d as o3d

        rm, surf = self._rm, self._surf
        self._clear()
        self._scene = scene
        centre, t_a, t_b, n = (x[0] for x in surf.frame(surf.centre()))
        self._render_from_world = _render_from_world(n, centre, scene.ambient.rotation_deg)
        objects = build_surroundings(scene, rm, surf)
        materials = self._materials(scene)
        tile = self.cfg.texture_size_px * scene.rebar.texel_m
        for kind, (mesh, uv_m) in self._rebar_meshes.items():
            mesh.triangle_uvs = _vec2(uv_m / tile)
            if kind == "bar":
                mesh.vertex_colors = o3d.utility.Vector3dVector(self._bar_tints(scene))
            self._add(kind, mesh, materials["rebar" if kind == "bar" else "tie_wire"], cast=True)
        for obj in objects:
            size = scene.ground.texture_size_m if obj.material == "ground" else tile
            if obj.material in ("concrete", "plywood"):
                size = 1.0
            self._add(obj.name, _o3d_mesh(obj, size), materials[obj.material], cast=obj.cast_shadows)
        self._set_lights(scene, (centre, t_a, t_b, n))
        bg = np.array(scene.background_rgb, np.float32)
        self._o3d.scene.set_background(np.append(bg, 1.0).astype(np.float32))
        self._build_raycast(objects)

    def _bar_tints(self, scene: SceneSample) -> np.ndarray:
        """Per-vertex colour of the merged bar mesh: one tint per bar, drawn from the scene's seed (a
        darker bar is a little warmer), scaled so the brightest is 1."""
        bars = [p for p in self._rm.parts if p.kind == "bar"]
        rgb = bar_tints(scene.rebar, len(bars), np.random.default_rng(scene.rebar.tint_seed))
        return np.repeat(rgb, [len(p.mesh.vertices) for p in bars], axis=0)

    def _add(self, name: str, mesh, material, *, cast: bool) -> None:
        scene = self._o3d.scene
        scene.add_geometry(name, mesh, material)
        scene.set_geometry_transform(name, self._render_from_world)
        scene.scene.geometry_shadows(name, cast, True)
        self._geometry.append(name)

    def _material(self, maps: dict[str, np.ndarray], *, colour=(1.0, 1.0, 1.0), metallic=1.0, roughness=1.0):
        """A defaultLit material: the maps (the same arrays give the same textures, see RenderConfig) times
        the scalar ``colour``, ``metallic`` and ``roughness``."""
        import open3d as o3d

        m = self._rendering.MaterialRecord()
        m.shader = "defaultLit"
        m.base_color = [*(float(c) for c in colour), 1.0]
        m.base_metallic = float(metallic) if "metallic" in maps else 0.0
        m.base_roughness = float(roughness) if "roughness" in maps else 0.7
        m.albedo_img = o3d.geometry.Image(np.ascontiguousarray(maps["albedo"]))
        if "roughness" in maps:
            m.roughness_img = o3d.geometry.Image(np.ascontiguousarray(maps["roughness"]))
        if "metallic" in maps:
            m.metallic_img = o3d.geometry.Image(np.ascontiguousarray(maps["metallic"]))
        if "normal" in maps:
            m.normal_img = o3d.geometry.Image(np.ascontiguousarray(maps["normal"]))
        return m

    def _rebar_look(self, r) -> dict[str, np.ndarray]:
        """The texture maps of a scene's rebar (procedural look or user set), cached by look."""
        size = self.cfg.texture_size_px
        if r.source == "user" and r.user_texture is not None:
            key = ("user", r.user_texture, r.texel_m, r.user_texture_size_m)
        else:
            key = ("procedural", r.look, r.texel_m)
        if key in self._rebar_maps:
            self._rebar_maps.move_to_end(key)
            return self._rebar_maps[key]
        if key[0] == "user":
            reps = max(1, int(round(size * r.texel_m / r.user_texture_size_m)))
            user = load_texture_set(r.user_texture, max(size // reps, 8))
            maps = {k: _tile(v, reps, size) for k, v in user.items()}
        else:
            fields = self._textures.get(f"rebar-{r.variant}-{size}", lambda: rebar_fields(r.variant, size))
            maps = rebar_maps(r, fields)
        self._rebar_maps[key] = maps
        while len(self._rebar_maps) > 4:  # a worker meets a scene again for its other trajectories
            self._rebar_maps.popitem(last=False)
        return maps

    def _materials(self, scene: SceneSample) -> dict:
        size = self.cfg.texture_size_px
        r = scene.rebar
        g = scene.ground
        if g.kind == "user" and g.user_texture is not None:
            ground = load_texture_set(g.user_texture, size)
        else:
            ground = self._ground_maps(g.kind, g.variant, size)
        b = min(g.brightness / 0.6, 1.5)
        dark = {
            "albedo": np.full((4, 4, 3), 48, np.uint8),
            "roughness": np.full((4, 4), 110, np.uint8),
            "metallic": np.full((4, 4), 150, np.uint8),
        }
        small = max(size // 2, 256)
        return {
            "rebar": self._material(
                self._rebar_look(r),
                colour=rebar_tint(r),
                metallic=r.metallic_scale,
                roughness=r.roughness_scale,
            ),
            "tie_wire": self._material(dark),
            "ground": self._material(ground, colour=(b, b, b)),
            "concrete": self._material(self._ground_maps("concrete", g.variant, small)),
            "plywood": self._material(self._ground_maps("plywood", g.variant, small)),
        }

    def _ground_maps(self, kind: str, variant: int, size: int) -> dict[str, np.ndarray]:
        return self._textures.get(f"{kind}-{variant}-{size}", lambda: ground_maps(kind, variant, size))

    def _set_lights(self, scene: SceneSample, frame) -> None:
        o3d_scene = self._o3d.scene.scene
        R, t = self._render_from_world[:3, :3], self._render_from_world[:3, 3]
        lights, ibl_intensity, _ = light_specs(scene, frame)
        shadows = self.cfg.shadows and scene.shadows
        for spec in lights:
            colour = spec.colour.astype(np.float32)
            direction = (R @ spec.direction).astype(np.float32)
            position = (R @ spec.position + t).astype(np.float32)
            cast = bool(shadows and spec.shadows)
            if spec.kind == "sun":
                o3d_scene.add_directional_light(spec.name, colour, direction, float(spec.intensity), cast)
            elif spec.kind == "point":
                o3d_scene.add_point_light(
                    spec.name, colour, position, float(spec.intensity), spec.falloff_m, cast
                )
            else:
                o3d_scene.add_spot_light(
                    spec.name,
                    colour,
                    position,
                    direction,
                    float(spec.intensity),
                    spec.falloff_m,
                    float(spec.inner_cone_rad),
                    float(spec.outer_cone_rad),
                    cast,
                )
            self._lights.append(spec.name)
        env = scene.ambient.environment
        if env != self._ibl:
            o3d_scene.set_indirect_light(str(_resources() / env))
            self._ibl = env
        o3d_scene.enable_indirect_light(True)
        o3d_scene.set_indirect_light_intensity(float(ibl_intensity))
        view = self._o3d.scene.view
        soft = scene.shadow_softness >= 0.5
        view_type = self._rendering.View.ShadowType.VSM if soft else self._rendering.View.ShadowType.PCF
        view.set_shadowing(bool(shadows), view_type)
        self._shadows_on = bool(shadows)

    # --- per frame ------------------------------------------------------------------------------------

    def render_raw(self, world_from_camera: np.ndarray) -> np.ndarray:
        """The rendered image before sensor effects: (H, W, 3) float32, linear light in [0, 1]."""
        if self._scene is None:
            raise RuntimeError("set_mesh(rm) and set_scene(scene) must come before render")
        k = self.intrinsics
        # explicit clipping planes: setup_camera(K, extrinsic, w, h) takes them from the scene's bounds,
        # which Open3D grows with every geometry ever added, so frames would depend on earlier scenes
        render_from_camera = self._render_from_world @ np.asarray(world_from_camera, float)
        self._o3d.setup_camera(k.K, np.linalg.inv(render_from_camera), k.width, k.height)
        self._o3d.scene.camera.set_projection(k.K, NEAR_M, FAR_M, float(k.width), float(k.height))
        self._warm_shadows()
        img = np.asarray(self._o3d.render_to_image())[..., :3].astype(np.float32) / 255.0
        if self.cfg.post_processing:  # Filament encoded it for display: back to linear
            img = np.where(img <= 0.04045, img / 12.92, ((img + 0.055) / 1.055) ** 2.4).astype(np.float32)
        return img

    def _warm_shadows(self) -> None:
        """Render (and drop) the process's first frame with shadows: only later ones are reproducible."""
        global _SHADOWS_WARM
        if not _SHADOWS_WARM and self._shadows_on:
            self._o3d.render_to_image()
            _SHADOWS_WARM = True

    def render(self, world_from_camera: np.ndarray, sensor: SensorSample, rng: np.random.Generator) -> Frame:
        """RGB (after ``sensor`` effects, noise from ``rng``), depth and instance ids of one camera pose."""
        with self.timer("filament"):
            raw = self.render_raw(world_from_camera)
        return self._finish_frame(raw, world_from_camera, sensor, rng)

    def close(self) -> None:
        """Drop this renderer's geometry and lights; the process keeps the OffscreenRenderer for reuse."""
        if self in _OPEN:
            self._clear()
            self._raycast = None
            _OPEN.remove(self)

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _vec2(a: np.ndarray):
    import open3d as o3d

    return o3d.utility.Vector2dVector(np.ascontiguousarray(a, np.float64))


def _o3d_mesh(obj: SceneObject, tile_m: float):
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(obj.shape.vertices),
        o3d.utility.Vector3iVector(obj.shape.triangles.astype(np.int32)),
    )
    mesh.compute_vertex_normals()
    mesh.triangle_uvs = _vec2(obj.shape.corner_uv_m.reshape(-1, 2) / tile_m)
    return mesh


def _tile(img: np.ndarray, reps: int, size: int) -> np.ndarray:
    out = np.tile(img, (reps, reps) + (1,) * (img.ndim - 2))
    if out.shape[0] != size:
        import cv2

        out = cv2.resize(out, (size, size), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(out)
