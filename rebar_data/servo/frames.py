"""Camera frames for the servo loop: the project's renderer (the detector's own domain) or a fast ray cast.

Both sources return what the eye-in-hand RGB-D camera would report: an RGB image and the metric depth
image of its depth sensor model (:func:`rebar_data.render.depth_sensor.sense_depth`; the suite's
``camera.depth_sensor``, Kinect v1-like structured light by default).

- ``renderer``: :class:`rebar_data.render.renderer.Renderer` with the dataset's materials and lights, so
  a trained detector sees images like those it was trained on.
- ``raycast``: exact geometry from the labels' own ray caster (:class:`rebar_data.render.raycast.Raycaster`),
  shaded with a headlight and a key light. About ten times cheaper; for tests and for suites whose detector
  does not look at pixels (``ground_truth``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from rebar_data.camera import Intrinsics
from rebar_data.config import ConfigError
from rebar_data.geometry.build import RebarMesh
from rebar_data.render.depth_sensor import sense_depth
from rebar_data.render.raycast import Raycaster
from rebar_data.scene.config import SceneConfig
from rebar_data.scene.sample import DepthSensorSample, nominal_depth_sensor


@dataclass(frozen=True)
class CameraFrame:
    """One camera frame: RGB (H, W, 3) uint8 and the sensor's metric z depth (H, W) float32, 0 = none."""

    rgb: np.ndarray
    depth_m: np.ndarray


class FrameSource(Protocol):
    def render(self, world_from_camera: np.ndarray, rng: np.random.Generator) -> CameraFrame: ...

    def cast_rays(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit per world ray against everything the frames show: distance (inf: none), instance id."""
        ...

    def close(self) -> None: ...


class RaycastFrames:
    """Frames shaded from an exact ray cast: rebar in a rust colour, a uniform dark background."""

    def __init__(
        self,
        rm: RebarMesh,
        camera: Intrinsics,
        raycaster: Raycaster,
        *,
        depth_sensor: DepthSensorSample | None = None,
    ):
        self.camera = camera
        self._raycaster = raycaster
        self._dirs_camera = camera.pixel_rays(unit=True).astype(np.float32)
        self._rays = np.empty((len(self._dirs_camera), 6), np.float32)
        self._albedo = np.array([150.0, 95.0, 62.0], np.float32)
        self._background = np.array([38.0, 40.0, 44.0], np.float32)
        self._depth_sensor = (
            depth_sensor if depth_sensor is not None else nominal_depth_sensor("structured_light")
        )

    def render(self, world_from_camera: np.ndarray, rng: np.random.Generator) -> CameraFrame:
        cam = self.camera
        R = world_from_camera[:3, :3].astype(np.float32)
        rays = self._rays
        rays[:, :3] = world_from_camera[:3, 3]
        np.matmul(self._dirs_camera, R.T, out=rays[:, 3:])
        t, normal = self._raycaster.cast_t_normal(rays)
        hit = np.isfinite(t)
        z = np.where(hit, t * self._dirs_camera[:, 2], 0.0)
        # Lambertian shading: a headlight (the ray itself) and a key light from the upper left.
        key = R @ np.array([-0.4, -0.6, 0.7], np.float32)
        key /= np.linalg.norm(key)
        facing = np.abs(np.einsum("ij,ij->i", normal, rays[:, 3:]))
        keyed = np.abs(normal @ key)
        shade = 0.25 + 0.45 * facing + 0.35 * keyed
        rgb = np.where(hit[:, None], shade[:, None] * self._albedo, self._background)
        rgb += rng.standard_normal(rgb.shape, dtype=np.float32) * 1.5
        rgb = np.clip(rgb, 0, 255).astype(np.uint8).reshape(cam.height, cam.width, 3)
        depth = sense_depth(z.reshape(cam.height, cam.width), self._depth_sensor, rng, fx=cam.fx)
        return CameraFrame(rgb, depth)

    def cast_rays(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._raycaster.cast_rays(origins, dirs)

    def close(self) -> None:
        pass


class RendererFrames:
    """Frames from the project's renderer: one sampled scene (lights, materials, surroundings, distractors)
    per run and one sampled sensor (exposure, noise, vignetting, JPEG) per episode, without the random
    per-frame motion blur and defocus of the dataset (the servo camera's blur would follow its motion).

    ``scene`` is what the scene is drawn from (a suite's ``scene`` section, the dataset's defaults when it
    has none); its sensor's motion-blur and defocus probabilities are set to zero whatever it says."""

    def __init__(
        self,
        rm: RebarMesh,
        camera: Intrinsics,
        rng: np.random.Generator,
        *,
        shadows: bool = False,
        depth_sensor: DepthSensorSample | None = None,
        scene: SceneConfig | None = None,
    ):
        try:
            from rebar_data.render.renderer import Renderer
            from rebar_data.scene.config import RenderConfig
            from rebar_data.scene.sample import sample_scene, sample_sensor
        except ImportError as e:
            raise ConfigError(
                f"frames = 'renderer' needs the project's renderer (rebar_data.render), which cannot be "
                f"imported here ({e}); accepted: frames: raycast"
            ) from None
        self.camera = camera
        self._renderer = Renderer(camera, RenderConfig(shadows=shadows))
        self._renderer.set_mesh(rm)
        scene = scene if scene is not None else SceneConfig()
        sensor = scene.sensor.model_copy(update={"motion_blur_probability": 0.0, "defocus_probability": 0.0})
        self._scene_cfg = scene.model_copy(update={"sensor": sensor})
        self._renderer.set_scene(sample_scene(self._scene_cfg, rng))
        self._sample_sensor = sample_sensor
        self.new_sensor(rng)
        self._depth_sensor = (
            depth_sensor if depth_sensor is not None else nominal_depth_sensor("structured_light")
        )

    def new_sensor(self, rng: np.random.Generator) -> None:
        """Draw the camera's sensor settings (done per episode)."""
        self._sensor = self._sample_sensor(self._scene_cfg, rng)

    def render(self, world_from_camera: np.ndarray, rng: np.random.Generator) -> CameraFrame:
        f = self._renderer.render(world_from_camera, self._sensor, rng)
        depth = sense_depth(np.asarray(f.depth_m), self._depth_sensor, rng, fx=self.camera.fx)
        return CameraFrame(np.ascontiguousarray(f.rgb[..., :3]), depth)

    def cast_rays(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._renderer.cast_rays(origins, dirs)

    def close(self) -> None:
        self._renderer.close()
