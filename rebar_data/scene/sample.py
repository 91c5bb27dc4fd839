"""Draw every randomized choice of a scene (lights, rebar material, surroundings) and of a frame's sensors
(the colour camera's effects and the depth sensor).

Every value is drawn whether it ends up used or not, in a fixed order, so one option's setting never
shifts another's draws, and ``record()`` has the same columns for every sample of a config.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from rebar_data.scene.config import (
    DEPTH_MODELS,
    GROUND_KINDS,
    LAMP_KINDS,
    DepthSensorConfig,
    LightingConfig,
    RebarMaterialConfig,
    SceneConfig,
    SensorConfig,
    SurroundingsConfig,
)
from rebar_data.scene.texture_folders import TextureSet, find_texture_sets

Record = dict[str, float | int | str | bool]


def _u(rng: np.random.Generator, r: tuple[float, float]) -> float:
    return float(rng.uniform(r[0], r[1])) if r[1] > r[0] else float(r[0])


def _int(rng: np.random.Generator, r: tuple[int, int]) -> int:
    return int(rng.integers(r[0], r[1] + 1))


def _choice(rng: np.random.Generator, table: dict[str, float], order: tuple[str, ...]) -> str:
    names = [k for k in order if table.get(k, 0.0) > 0]
    w = np.array([table[k] for k in names], float)
    return names[int(rng.choice(len(names), p=w / w.sum()))]


def _flat(prefix: str, obj: object) -> Record:
    out: Record = {}
    for f in fields(obj):  # type: ignore[arg-type]
        v = getattr(obj, f.name)
        if v is None or isinstance(v, TextureSet | tuple):  # paths and nested values are not columns
            continue
        out[f"{prefix}{f.name}"] = v.item() if isinstance(v, np.generic) else v
    return out


@dataclass(frozen=True)
class LightSample:
    """One light, placed in the mat's frame. ``kind`` is ``none`` for an unused slot."""

    kind: str  # "sun" | "point" | "spot" | "area" | "none"
    azimuth_deg: float
    elevation_deg: float
    distance_m: float  # from the mat's centre (point, spot, area)
    illuminance_lux: float  # on a surface facing the light at the mat's centre
    temperature_k: float
    cone_deg: float  # spot: full outer cone
    size_m: float  # area: side of the panel
    grid: int  # area: spots per side
    shadows: bool


@dataclass(frozen=True)
class AmbientSample:
    environment: str
    illuminance_lux: float
    rotation_deg: float


@dataclass(frozen=True)
class MaterialSample:
    """The rebar's look: a texture look (pattern variant and layer levels) or a user texture set, with
    per-scene scalars on top (tint, metallic and roughness scales) and a seed for per-bar tints."""

    source: str  # "procedural" | "user"
    user_set: str  # the user set's name, "" for procedural
    variant: int  # which seeded noise pattern
    rust: float
    mill_scale: float
    dust: float
    pitting: float
    wear: float
    hue_shift: float  # in [-1, 1]: towards yellow-brown (+) or red-brown (-) rust
    brightness: float
    metallic_scale: float
    roughness_scale: float
    colour_variation: float  # per-bar tint strength
    tint_seed: int
    texel_m: float
    user_texture_size_m: float
    user_texture: TextureSet | None = None

    @property
    def look(self) -> tuple:
        """What the texture maps depend on (every other field is applied on top of them)."""
        return (self.variant, self.rust, self.mill_scale, self.dust, self.pitting, self.wear)


@dataclass(frozen=True)
class GroundSample:
    kind: str  # "concrete" | "soil" | "plywood" | "gravel" | "user"
    user_set: str
    shape: str  # "plane" | "follow"
    distance_m: float
    tilt_deg: float
    tilt_azimuth_deg: float
    texture_size_m: float
    variant: int
    brightness: float  # albedo scale
    size_m: float  # side of the ground plane
    user_texture: TextureSet | None = None


@dataclass(frozen=True)
class DistractorSample:
    lower_layer: bool
    lower_layer_depth_m: float
    lower_layer_shift_a_m: float
    lower_layer_shift_b_m: float
    spacers: int
    loose_tie_wire: int
    formwork_sides: int  # bit mask: a-, a+, b-, b+
    seed: int


@dataclass(frozen=True)
class SceneSample:
    """Every randomized choice for one scene: lights, rebar material, surroundings and distractors."""

    sun: LightSample
    lamps: tuple[LightSample, ...]  # padded with kind "none" to the config's largest count
    ambient: AmbientSample
    shadows: bool
    shadow_softness: float
    exposure_lux: float
    rebar: MaterialSample
    ground: GroundSample
    distractors: DistractorSample
    background_rgb: tuple[float, float, float]

    def record(self) -> Record:
        """Flat columns: ``light_*``, ``mat_*``, ``surr_*``; the same keys for every sample of a config."""
        r: Record = {}
        r.update(_flat("light_sun_", self.sun))
        for i, lamp in enumerate(self.lamps):
            r.update(_flat(f"light_lamp{i}_", lamp))
        r.update(_flat("light_ambient_", self.ambient))
        r["light_shadows"] = self.shadows
        r["light_shadow_softness"] = self.shadow_softness
        r["light_exposure_lux"] = self.exposure_lux
        r.update(_flat("mat_", self.rebar))
        r.update(_flat("surr_ground_", self.ground))
        r.update(_flat("surr_", self.distractors))
        r.update({f"surr_background_{c}": float(v) for c, v in zip("rgb", self.background_rgb, strict=True)})
        return r


@dataclass(frozen=True)
class SensorSample:
    """Per-frame camera effects. A blur of 0 px or a JPEG quality of 0 means the effect is off."""

    exposure_ev: float
    shot_noise: float
    read_noise: float
    defocus_radius_px: float
    motion_blur_px: float
    motion_blur_angle_deg: float
    vignetting: float
    jpeg_quality: int

    def record(self) -> Record:
        return _flat("sensor_", self)


def _light(rng: np.random.Generator, kind: str, cfg, *, present: bool, lamp: bool) -> LightSample:
    az = _u(rng, cfg.azimuth_deg)
    el = _u(rng, cfg.elevation_deg)
    lux = _u(rng, cfg.illuminance_lux)
    temp = _u(rng, cfg.temperature_k)
    dist = _u(rng, cfg.distance_m) if lamp else 0.0
    cone = _u(rng, cfg.spot_cone_deg) if lamp else 0.0
    size = _u(rng, cfg.area_size_m) if lamp else 0.0
    shadow = bool(rng.random() < cfg.shadow_probability) if lamp else True
    if not present:
        return LightSample("none", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, False)
    return LightSample(
        kind,
        az,
        el,
        dist,
        lux,
        temp,
        cone if kind == "spot" else 0.0,
        size if kind == "area" else 0.0,
        cfg.area_grid if kind == "area" else 0,
        shadow,
    )


def _lighting(cfg: LightingConfig, rng: np.random.Generator):
    sun_on = bool(rng.random() < cfg.sun.probability)
    sun = _light(rng, "sun", cfg.sun, present=sun_on, lamp=False)
    n_lamps = _int(rng, cfg.lamps.count)
    lamps = []
    for i in range(cfg.lamps.count[1]):
        kind = _choice(rng, cfg.lamps.kinds, LAMP_KINDS)
        lamps.append(_light(rng, kind, cfg.lamps, present=i < n_lamps, lamp=True))
    env = cfg.ambient.environments[int(rng.integers(len(cfg.ambient.environments)))]
    ambient = AmbientSample(env, _u(rng, cfg.ambient.illuminance_lux), _u(rng, cfg.ambient.rotation_deg))
    shadows = bool(rng.random() < cfg.shadows.probability)
    softness = _u(rng, cfg.shadows.softness)
    return sun, tuple(lamps), ambient, shadows, softness


def _user_sets(dirs) -> list[TextureSet]:
    return [ts for d in dirs for ts in find_texture_sets(d)]


def _level(rng: np.random.Generator, levels: list[float]) -> float:
    return float(levels[int(rng.integers(len(levels)))])


def _material(cfg: RebarMaterialConfig, rng: np.random.Generator) -> MaterialSample:
    sets = _user_sets(cfg.texture_dirs)
    use_user = bool(rng.random() < cfg.user_texture_probability) and bool(sets)
    pick = int(rng.integers(max(len(sets), 1)))
    values = dict(
        variant=int(rng.integers(cfg.variants)),
        rust=_level(rng, cfg.rust),
        mill_scale=_level(rng, cfg.mill_scale),
        dust=_level(rng, cfg.dust),
        pitting=cfg.pitting,
        wear=cfg.wear,
        hue_shift=_u(rng, cfg.hue_shift),
        brightness=_u(rng, cfg.brightness),
        metallic_scale=_u(rng, cfg.metallic_scale),
        roughness_scale=_u(rng, cfg.roughness_scale),
        colour_variation=_u(rng, cfg.colour_variation),
        tint_seed=int(rng.integers(2**31)),
        texel_m=cfg.texel_m,
        user_texture_size_m=cfg.user_texture_size_m,
    )
    if use_user:
        return MaterialSample("user", sets[pick].name, user_texture=sets[pick], **values)
    return MaterialSample("procedural", "", **values)


def _ground(cfg: SurroundingsConfig, rng: np.random.Generator) -> GroundSample:
    g = cfg.ground
    sets = _user_sets(g.texture_dirs)
    use_user = bool(rng.random() < g.user_texture_probability) and bool(sets)
    pick = int(rng.integers(max(len(sets), 1)))
    kind = _choice(rng, g.kinds, GROUND_KINDS)
    shape = _choice(rng, g.shapes, ("plane", "follow"))
    values = dict(
        shape=shape,
        distance_m=_u(rng, g.distance_m),
        tilt_deg=_u(rng, g.tilt_deg),
        tilt_azimuth_deg=float(rng.uniform(0.0, 360.0)),
        texture_size_m=_u(rng, g.texture_size_m),
        variant=int(rng.integers(g.variants)),
        brightness=_u(rng, cfg.background_brightness),
        size_m=g.size_m,
    )
    if use_user:
        return GroundSample("user", sets[pick].name, user_texture=sets[pick], **values)
    return GroundSample(kind, "", **values)


def _distractors(cfg: SurroundingsConfig, rng: np.random.Generator) -> DistractorSample:
    d = cfg.distractors
    lower = bool(rng.random() < d.lower_layer_probability)
    depth = _u(rng, d.lower_layer_depth_m)
    shift = rng.uniform(-0.05, 0.05, 2)
    spacers = _int(rng, d.spacers)
    wire = _int(rng, d.loose_tie_wire)
    sides = int(sum(1 << i for i in range(4) if rng.random() < d.formwork_probability))
    return DistractorSample(
        lower, depth, float(shift[0]), float(shift[1]), spacers, wire, sides, int(rng.integers(2**31))
    )


def sample_scene(cfg: SceneConfig, rng: np.random.Generator) -> SceneSample:
    """Draw one scene: lights, rebar material, ground, background and distractors."""
    sun, lamps, ambient, shadows, softness = _lighting(cfg.lighting, rng)
    rebar = _material(cfg.materials.rebar, rng)
    ground = _ground(cfg.surroundings, rng)
    distractors = _distractors(cfg.surroundings, rng)
    grey = _u(rng, cfg.surroundings.background_brightness)
    tint = rng.uniform(-0.08, 0.08, 3)
    background = tuple(float(np.clip(grey * (1.0 + t), 0.0, 1.0)) for t in tint)
    return SceneSample(
        sun,
        lamps,
        ambient,
        shadows,
        softness,
        cfg.lighting.exposure_lux,
        rebar,
        ground,
        distractors,
        background,
    )


def sample_sensor(cfg: SceneConfig | SensorConfig, rng: np.random.Generator) -> SensorSample:
    """Draw one frame's sensor effects (``cfg`` is the scene config or its ``sensor`` section)."""
    s = cfg.sensor if isinstance(cfg, SceneConfig) else cfg
    exposure = _u(rng, s.exposure_ev)
    shot = _u(rng, s.shot_noise)
    read = _u(rng, s.read_noise)
    defocus_on = bool(rng.random() < s.defocus_probability)
    defocus = _u(rng, s.defocus_radius_px)
    motion_on = bool(rng.random() < s.motion_blur_probability)
    motion = _u(rng, s.motion_blur_px)
    angle = float(rng.uniform(0.0, 180.0))
    vignetting = _u(rng, s.vignetting)
    jpeg_on = bool(rng.random() < s.jpeg_probability)
    quality = _int(rng, s.jpeg_quality)
    return SensorSample(
        exposure_ev=exposure,
        shot_noise=shot,
        read_noise=read,
        defocus_radius_px=defocus if defocus_on else 0.0,
        motion_blur_px=motion if motion_on else 0.0,
        motion_blur_angle_deg=angle if motion_on else 0.0,
        vignetting=vignetting,
        jpeg_quality=quality if jpeg_on else 0,
    )


@dataclass(frozen=True)
class DepthSensorSample:
    """One frame's depth sensor: its model and drawn parameters (0 where the model has no such parameter).

    ``baseline_m`` is the projector's (structured light) or the second imager's (active stereo) offset along
    the camera's +x; ``noise`` is the model's noise level: a scale of the axial sigma (structured light), the
    disparity sigma in pixels (active stereo) or the axial sigma at 1 m in metres (time of flight).
    """

    model: str  # "exact" | "structured_light" | "active_stereo" | "time_of_flight"
    baseline_m: float
    focal_px: float
    disparity_step_px: float
    window_px: int
    noise: float
    noise_per_m: float
    flying_pixel_probability: float
    edge_jump_m: float
    near_m: float
    far_m: float
    shift_x_px: float  # depth-to-colour misregistration
    shift_y_px: float

    def record(self) -> Record:
        return _flat("sensor_depth_", self)


def _odd_window(rng: np.random.Generator, r: tuple[int, int]) -> int:
    return int(r[0] + 2 * rng.integers(0, (r[1] - r[0]) // 2 + 1))


def sample_depth_sensor(cfg: SceneConfig | DepthSensorConfig, rng: np.random.Generator) -> DepthSensorSample:
    """Draw one frame's depth sensor (``cfg`` is the scene config or its ``depth_sensor`` section)."""
    d = cfg.depth_sensor if isinstance(cfg, SceneConfig) else cfg
    model = _choice(rng, d.models, DEPTH_MODELS)
    sl, st, tof = d.structured_light, d.active_stereo, d.time_of_flight
    sl_window, sl_noise = _odd_window(rng, sl.window_px), _u(rng, sl.noise_scale)
    st_window, st_noise = _odd_window(rng, st.window_px), _u(rng, st.subpixel_px)
    tof_noise, tof_fly = _u(rng, tof.noise_m), _u(rng, tof.flying_pixel_probability)
    shift = _u(rng, d.misregistration_px)
    angle = float(rng.uniform(0.0, 2.0 * np.pi))
    dx, dy = shift * float(np.cos(angle)), shift * float(np.sin(angle))
    zero = dict(
        baseline_m=0.0,
        focal_px=0.0,
        disparity_step_px=0.0,
        window_px=0,
        noise=0.0,
        noise_per_m=0.0,
        flying_pixel_probability=0.0,
        edge_jump_m=0.0,
        near_m=0.0,
        far_m=0.0,
    )
    if model == "structured_light":
        zero.update(
            baseline_m=sl.baseline_m,
            focal_px=sl.focal_px,
            disparity_step_px=sl.disparity_step_px,
            window_px=sl_window,
            noise=sl_noise,
            near_m=sl.range_m[0],
            far_m=sl.range_m[1],
        )
    elif model == "active_stereo":
        zero.update(
            baseline_m=st.baseline_m,
            focal_px=st.focal_px,
            window_px=st_window,
            noise=st_noise,
            near_m=st.focal_px * st.baseline_m / st.max_disparity_px,
            far_m=st.far_m,
        )
    elif model == "time_of_flight":
        zero.update(
            noise=tof_noise,
            noise_per_m=tof.noise_per_m,
            flying_pixel_probability=tof_fly,
            edge_jump_m=tof.edge_jump_m,
            near_m=tof.range_m[0],
            far_m=tof.range_m[1],
        )
    return DepthSensorSample(model=model, shift_x_px=dx, shift_y_px=dy, **zero)


def nominal_depth_sensor(
    model: str, cfg: DepthSensorConfig | None = None, *, noise: bool = True
) -> DepthSensorSample:
    """A depth sensor at fixed parameters (no draw): the middle of each range, the largest window, no
    misregistration; ``noise`` false zeroes its noise. For a camera that stays one device (the robot's)."""
    d = cfg if cfg is not None else DepthSensorConfig()
    if model not in DEPTH_MODELS:
        raise ValueError(f"depth sensor model {model!r} is unknown; accepted: {', '.join(DEPTH_MODELS)}")
    mid = {
        "structured_light": {"window_px": (d.structured_light.window_px[1],) * 2},
        "active_stereo": {"window_px": (d.active_stereo.window_px[1],) * 2},
    }
    fixed = d.model_copy(
        update={
            "models": {model: 1.0},
            "misregistration_px": (0.0, 0.0),
            "structured_light": d.structured_light.model_copy(update=mid["structured_light"]),
            "active_stereo": d.active_stereo.model_copy(update=mid["active_stereo"]),
        }
    )
    s = sample_depth_sensor(fixed, _Middle())
    return replace(s, noise=0.0, noise_per_m=0.0) if not noise else s


class _Middle:
    """A stand-in generator that draws the middle of every range (and the first choice)."""

    def uniform(self, low=0.0, high=1.0, size=None):
        return 0.0 if (low, high) == (0.0, 2.0 * np.pi) else (low + high) / 2.0

    def integers(self, low, high=None, size=None):
        return 0

    def choice(self, n, p=None):
        return int(np.argmax(p)) if p is not None else 0
