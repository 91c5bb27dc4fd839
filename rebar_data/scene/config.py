"""Config models of a pipeline's ``camera``, ``scene`` and ``render`` sections.

Every randomized quantity is a ``(min, max)`` range drawn uniformly (per scene for lights, materials and
surroundings; per frame for sensor effects), or a ``{choice: weight}`` table. The defaults follow the
paper's set-up (a rebar mat on site, a sun and two more lights, three camera trajectories, 1200 images)
and widen it where the paper leaves the choice open. Units are SI unless the name says otherwise
(``_deg``, ``_px``, ``_k`` for kelvin, ``_lux``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, get_args

from pydantic import AfterValidator, Field, ValidationError, field_validator, model_validator

from rebar_data.config import Fraction, NonNegative, Positive, Strict, excerpt


def _ordered(r: tuple[float, float]) -> tuple[float, float]:
    if r[0] > r[1]:
        raise ValueError(f"range {list(r)} has min > max; accepted: [min, max] with min <= max")
    return r


Range = Annotated[tuple[float, float], AfterValidator(_ordered)]
PositiveRange = Annotated[tuple[Positive, Positive], AfterValidator(_ordered)]
NonNegativeRange = Annotated[tuple[NonNegative, NonNegative], AfterValidator(_ordered)]
FractionRange = Annotated[tuple[Fraction, Fraction], AfterValidator(_ordered)]
CountRange = Annotated[
    tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0)]], AfterValidator(_ordered)
]


def _weights(table: dict[str, float], accepted: tuple[str, ...]) -> dict[str, float]:
    unknown = sorted(set(table) - set(accepted))
    if unknown:
        raise ValueError(f"unknown choice {excerpt(unknown[0])}; accepted: {', '.join(accepted)}")
    if any(w < 0 for w in table.values()) or sum(table.values()) <= 0:
        raise ValueError(f"weights {excerpt(table)} must be >= 0 with a positive sum")
    return table


# --- camera -------------------------------------------------------------------------------------------

INTRINSICS_PRESETS = ("kinect_v1", "realsense_color", "square_640")


class ExplicitIntrinsics(Strict):
    """A pinhole camera in pixels, COCO corner origin (``u = fx * x / z + cx``)."""

    width: Annotated[int, Field(gt=0, le=8192)]
    height: Annotated[int, Field(gt=0, le=8192)]
    fx: Positive
    fy: Positive
    cx: float
    cy: float


class TrajectoryBase(Strict):
    """What every trajectory kind has.

    ``standoff_m`` is the distance from the camera to the point of the mat it looks at. ``tilt_deg`` is the
    angle between the optical axis and the mat's inward normal there (0 = looking straight at the mat).
    ``roll_deg`` turns the image about the optical axis. Targets are points of the mat at least
    ``edge_margin_m`` inside its crossings' outline, so most frames are full of rebar. The default
    stand-offs put 12 mm bars 6-17 px wide on a 525 px focal length and 20-130 crossings in a 640x640
    frame (median 40-60), so a detector can place crossings to a pixel or two.
    """

    count: Annotated[int, Field(ge=1)] = 20
    frames: Annotated[int, Field(ge=1)] = 20
    standoff_m: PositiveRange = (0.35, 0.7)
    tilt_deg: Annotated[tuple[float, float], AfterValidator(_ordered)] = (0.0, 30.0)
    roll_deg: Range = (-180.0, 180.0)
    edge_margin_m: NonNegative = 0.3

    @field_validator("tilt_deg")
    @classmethod
    def _tilt(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] < 0 or v[1] >= 85:
            raise ValueError(f"{list(v)} is not accepted: tilts must lie in [0, 85) degrees")
        return v


class OrbitArc(TrajectoryBase):
    """The camera sweeps ``sweep_deg`` of azimuth around one target on the mat at a fixed tilt and stand-off."""

    kind: Literal["orbit_arc"]
    standoff_m: PositiveRange = (0.35, 0.65)
    sweep_deg: Annotated[tuple[float, float], AfterValidator(_ordered)] = (45.0, 120.0)
    tilt_deg: Annotated[tuple[float, float], AfterValidator(_ordered)] = (10.0, 30.0)


class StraightPass(TrajectoryBase):
    """The camera crosses the mat in a straight line of ``length_m`` (at most the mat's extent along its
    heading), at the stand-off, looking at it."""

    kind: Literal["straight_pass"]
    length_m: PositiveRange = (0.8, 2.0)
    tilt_deg: Annotated[tuple[float, float], AfterValidator(_ordered)] = (0.0, 25.0)


class Approach(TrajectoryBase):
    """The camera descends towards one target from the far end of ``standoff_m`` to the near end."""

    kind: Literal["approach"]
    standoff_m: PositiveRange = (0.35, 0.8)
    tilt_deg: Annotated[tuple[float, float], AfterValidator(_ordered)] = (0.0, 20.0)


class RandomLookAt(TrajectoryBase):
    """Independent poses: a random target, tilt, azimuth, roll and stand-off per frame."""

    kind: Literal["random_look_at"]
    tilt_deg: Annotated[tuple[float, float], AfterValidator(_ordered)] = (0.0, 35.0)


TrajectoryConfig = Annotated[OrbitArc | StraightPass | Approach | RandomLookAt, Field(discriminator="kind")]


def _default_trajectories() -> list:
    return [OrbitArc(kind="orbit_arc"), StraightPass(kind="straight_pass"), Approach(kind="approach")]


class CameraConfig(Strict):
    """The pipeline's ``camera`` section: intrinsics (a preset or explicit) and the trajectories to film.

    The default is the paper's: three trajectory kinds, 1200 images (20 instances of 20 frames each).
    """

    intrinsics: Literal["kinect_v1", "realsense_color", "square_640"] | ExplicitIntrinsics = "square_640"
    trajectories: Annotated[list[TrajectoryConfig], Field(min_length=1)] = Field(
        default_factory=_default_trajectories
    )

    @field_validator("intrinsics", mode="before")
    @classmethod
    def _preset(cls, v: object) -> object:
        if isinstance(v, str) and v not in INTRINSICS_PRESETS:
            raise ValueError(
                f"{excerpt(v)} is not a preset; accepted: {', '.join(INTRINSICS_PRESETS)}, or a mapping of width, "
                "height, fx, fy, cx, cy"
            )
        if isinstance(v, dict):  # validate here, so an error names the key rather than the union's branches
            try:
                return ExplicitIntrinsics.model_validate(v)
            except ValidationError as e:
                err = e.errors(include_url=False)[0]
                key = ".".join(str(x) for x in err["loc"])
                given = f" = {excerpt(err['input'])}" if err["type"] != "missing" else ""
                raise ValueError(f"{key}{given}: {err['msg'].lower()}") from None
        return v


# --- lighting -----------------------------------------------------------------------------------------

# Open3D's bundled image-based lights (open3d/resources/<name>_ibl.ktx)
Environment = Literal[
    "default",
    "brightday",
    "crossroads",
    "hall",
    "konzerthaus",
    "nightlights",
    "park",
    "park2",
    "pillars",
    "streetlamp",
]
ENVIRONMENTS: tuple[str, ...] = get_args(Environment)
LAMP_KINDS = ("point", "spot", "area")


class SunConfig(Strict):
    """Directional light. Azimuth and elevation are measured in the mat's frame (elevation 90 = along the
    mat's outward normal), so the lit side is the side the cameras see."""

    probability: Fraction = 1.0
    azimuth_deg: Range = (0.0, 360.0)
    elevation_deg: Range = (20.0, 85.0)
    illuminance_lux: PositiveRange = (20_000.0, 100_000.0)
    temperature_k: PositiveRange = (4500.0, 6500.0)

    @field_validator("elevation_deg")
    @classmethod
    def _elev(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] < 0 or v[1] > 90:
            raise ValueError(f"{list(v)} is not accepted: elevations must lie in [0, 90] degrees")
        return v


class LampConfig(Strict):
    """Point, spot and area lights placed around the mat, each giving ``illuminance_lux`` at its centre.

    Open3D has no area light: an area light is a grid of ``area_grid`` x ``area_grid`` wide spot lights
    (75 degree half-angle) spread over a panel of ``area_size_m`` facing the mat, its shadow soft. Each
    light costs about 0.05 s a frame on a CPU, so the default grid is 1 (one wide panel light).
    """

    count: CountRange = (2, 2)
    kinds: dict[str, float] = Field(default_factory=lambda: {"point": 1.0, "spot": 1.0, "area": 1.0})
    distance_m: PositiveRange = (1.0, 3.0)
    azimuth_deg: Range = (0.0, 360.0)
    elevation_deg: Range = (25.0, 85.0)
    illuminance_lux: PositiveRange = (5_000.0, 40_000.0)
    temperature_k: PositiveRange = (2700.0, 6500.0)
    spot_cone_deg: Annotated[tuple[float, float], AfterValidator(_ordered)] = (40.0, 90.0)
    area_size_m: PositiveRange = (0.3, 1.2)
    area_grid: Annotated[int, Field(ge=1, le=4)] = 1
    shadow_probability: Fraction = 0.3

    @field_validator("kinds")
    @classmethod
    def _kinds(cls, v: dict[str, float]) -> dict[str, float]:
        return _weights(v, LAMP_KINDS)

    @field_validator("spot_cone_deg")
    @classmethod
    def _cone(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] <= 0 or v[1] >= 170:
            raise ValueError(f"{list(v)} is not accepted: full cone angles must lie in (0, 170) degrees")
        return v


class AmbientConfig(Strict):
    """Image-based ambient light from one of Open3D's bundled environments, turned about the mat's normal.

    ``illuminance_lux`` is what the environment alone gives a surface facing up (the environments differ
    by ten times in brightness; each is calibrated to this).
    """

    environments: Annotated[list[Environment], Field(min_length=1)] = Field(
        default_factory=lambda: list(ENVIRONMENTS)
    )
    illuminance_lux: PositiveRange = (5_000.0, 30_000.0)
    rotation_deg: Range = (0.0, 360.0)


class ShadowConfig(Strict):
    """Shadows on with ``probability``; ``softness`` in [0, 1] (>= 0.5 uses soft variance shadow maps)."""

    probability: Fraction = 0.9
    softness: FractionRange = (0.0, 1.0)


class LightingConfig(Strict):
    """The lighting kit. The default is the paper's three light sources (a sun and two lamps) plus ambient.

    ``exposure_lux`` is the illuminance at the mat's centre the camera is exposed for: every light is scaled
    by one factor so their estimated sum there is this (as auto-exposure would), which keeps the 8-bit
    linear image the renderer reads back well within range. Only the lights' ratios change the look.
    """

    sun: SunConfig = SunConfig()
    lamps: LampConfig = LampConfig()
    ambient: AmbientConfig = AmbientConfig()
    shadows: ShadowConfig = ShadowConfig()
    exposure_lux: Positive = 100_000.0


# --- materials ----------------------------------------------------------------------------------------


def _texture_dir(p: Path) -> Path:
    from rebar_data.scene.texture_folders import find_texture_sets

    p = Path(p).expanduser()
    if not p.exists():
        raise ValueError(f"texture folder {str(p)!r} does not exist; accepted: a folder of texture maps")
    if not p.is_dir():
        raise ValueError(f"{str(p)!r} is not a folder; accepted: a folder of texture maps")
    if not find_texture_sets(p):
        raise ValueError(
            f"texture folder {str(p)!r} holds no texture maps; accepted: a folder with at least an albedo "
            "map (such as name_diff_1k.png, as Poly Haven ships them) and optionally _rough and _nor_gl maps"
        )
    return p


TextureDir = Annotated[Path, AfterValidator(_texture_dir)]


Levels = Annotated[list[Fraction], Field(min_length=1, max_length=8)]


class RebarMaterialConfig(Strict):
    """The material kit for bars: procedural PBR texture maps, or a user's texture maps.

    Procedural layers: ``rust`` (orange-brown, rough, with ``pitting``: dark corrosion pits with relief),
    ``mill_scale`` (the blue-grey oxide of new bars), ``dust`` (pale, matte) and ``wear`` (bright bare
    steel). Coverages are drawn from short lists of levels, because Open3D 0.19 keeps every distinct texture
    it has uploaded until the process ends: a worker holds at most ``variants`` x levels rebar looks (each
    three maps). Continuous variety comes on top of the maps, per scene: ``hue_shift`` (towards yellow
    (+) or red (-) rust), ``brightness``, ``metallic_scale`` and ``roughness_scale``, and per bar:
    ``colour_variation`` (a tint of each bar). Noise fields come from ``variants`` seeded patterns and are
    cached in memory and on disk. ``texture_dirs`` add user texture sets (albedo, roughness, normal maps)
    to the pool, drawn with ``user_texture_probability``; ``user_texture_size_m`` is what one map covers.
    """

    rust: Levels = Field(default_factory=lambda: [0.35, 0.65, 0.9])
    mill_scale: Levels = Field(default_factory=lambda: [0.2, 0.7])
    dust: Levels = Field(default_factory=lambda: [0.0, 0.25])
    pitting: Fraction = 0.4
    wear: Fraction = 0.1
    variants: Annotated[int, Field(ge=1, le=64)] = 4
    hue_shift: Annotated[tuple[float, float], AfterValidator(_ordered)] = (-1.0, 1.0)
    brightness: PositiveRange = (0.8, 1.15)
    metallic_scale: FractionRange = (0.5, 1.0)
    roughness_scale: PositiveRange = (0.85, 1.1)
    colour_variation: FractionRange = (0.03, 0.15)
    texel_m: Positive = 0.0015
    texture_dirs: list[TextureDir] = Field(default_factory=list)
    user_texture_probability: Fraction = 0.5
    user_texture_size_m: Positive = 0.5

    @field_validator("hue_shift")
    @classmethod
    def _hue(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] < -1 or v[1] > 1:
            raise ValueError(f"{list(v)} is not accepted: hue shifts must lie in [-1, 1]")
        return v


GROUND_KINDS = ("concrete", "soil", "plywood", "gravel")


class GroundConfig(Strict):
    """The surface behind the mat: a plane beneath its lowest bar, or one that follows its curvature.

    ``distance_m`` is the gap between the lowest bar and the surface. ``texture_dirs`` add the user's
    texture sets to the ground pool (drawn with ``user_texture_probability``).
    """

    kinds: dict[str, float] = Field(
        default_factory=lambda: {"concrete": 1.0, "soil": 1.0, "plywood": 1.0, "gravel": 1.0}
    )
    shapes: dict[str, float] = Field(default_factory=lambda: {"plane": 1.0, "follow": 1.0})
    distance_m: NonNegativeRange = (0.05, 0.6)
    tilt_deg: NonNegativeRange = (0.0, 5.0)
    size_m: Positive = 40.0
    texture_size_m: PositiveRange = (0.6, 1.5)
    variants: Annotated[int, Field(ge=1, le=64)] = 4
    texture_dirs: list[TextureDir] = Field(default_factory=list)
    user_texture_probability: Fraction = 0.5

    @field_validator("kinds")
    @classmethod
    def _kinds(cls, v: dict[str, float]) -> dict[str, float]:
        return _weights(v, GROUND_KINDS)

    @field_validator("shapes")
    @classmethod
    def _shapes(cls, v: dict[str, float]) -> dict[str, float]:
        return _weights(v, ("plane", "follow"))


class DistractorConfig(Strict):
    """Things on site that are not the mat's crossings: a lower bar layer, spacers, loose tie wire, formwork.

    The lower layer is a second mat ``lower_layer_depth_m`` beneath the top one (the element's other face).
    Spacers are concrete blocks under the mat; loose tie wire lies on the ground; formwork edges are
    plywood boards along the mat's sides, each side with ``formwork_probability``.
    """

    lower_layer_probability: Fraction = 0.3
    lower_layer_depth_m: PositiveRange = (0.1, 0.2)
    spacers: CountRange = (0, 12)
    loose_tie_wire: CountRange = (0, 15)
    formwork_probability: Fraction = 0.3


class SurroundingsConfig(Strict):
    """The surroundings: the ground behind the mat, the background colour, distractors."""

    ground: GroundConfig = GroundConfig()
    distractors: DistractorConfig = DistractorConfig()
    background_brightness: FractionRange = (0.3, 0.9)


class MaterialsConfig(Strict):
    rebar: RebarMaterialConfig = RebarMaterialConfig()


class SensorConfig(Strict):
    """Per-frame camera effects, applied to the rendered linear image in this order: defocus and motion blur,
    vignetting, exposure (``exposure_ev`` about the auto-exposure), shot and read noise, tone curve, JPEG."""

    exposure_ev: Range = (-0.7, 0.5)
    shot_noise: FractionRange = (0.002, 0.02)
    read_noise: FractionRange = (0.001, 0.008)
    defocus_probability: Fraction = 0.25
    defocus_radius_px: PositiveRange = (0.6, 2.0)
    motion_blur_probability: Fraction = 0.25
    motion_blur_px: PositiveRange = (1.0, 6.0)
    vignetting: FractionRange = (0.0, 0.4)
    jpeg_probability: Fraction = 0.5
    jpeg_quality: Annotated[
        tuple[Annotated[int, Field(ge=5, le=100)], Annotated[int, Field(ge=5, le=100)]],
        AfterValidator(_ordered),
    ] = (60, 95)


DEPTH_MODELS = ("exact", "structured_light", "active_stereo", "time_of_flight")


def _odd(r: tuple[int, int]) -> tuple[int, int]:
    if r[0] % 2 == 0 or r[1] % 2 == 0:
        raise ValueError(f"window {list(r)} has an even side; accepted: odd sides, such as [7, 9]")
    return r


OddWindow = Annotated[
    tuple[Annotated[int, Field(ge=1, le=31)], Annotated[int, Field(ge=1, le=31)]],
    AfterValidator(_ordered),
    AfterValidator(_odd),
]


class StructuredLightConfig(Strict):
    """A Kinect v1-like structured-light camera (sources in :mod:`rebar_data.render.depth_sensor`)."""

    baseline_m: Positive = 0.075  # projector to IR camera; the projector sits at +x of the camera
    focal_px: Positive = 580.0  # the IR camera's focal length, in which disparity is measured
    disparity_step_px: Positive = 0.125  # disparity quantisation
    window_px: OddWindow = (7, 9)  # correlation window side, drawn per frame (odd values)
    noise_scale: NonNegativeRange = (0.8, 1.2)  # times the axial noise sigma(z) of Nguyen et al. (2012)
    range_m: PositiveRange = (0.5, 4.5)  # nearest and farthest measured z


class ActiveStereoConfig(Strict):
    """A RealSense D4xx-like active stereo camera (sources in :mod:`rebar_data.render.depth_sensor`)."""

    baseline_m: Positive = 0.050  # left to right imager; depth is in the left imager's frame
    focal_px: Positive = 447.0  # the imagers' focal length at 848x480
    subpixel_px: NonNegativeRange = (0.05, 0.1)  # disparity noise sigma (RMS subpixel error)
    window_px: OddWindow = (5, 7)  # matching window side, drawn per frame (odd values)
    max_disparity_px: Positive = 126.0  # disparity search range; sets the nearest measured z
    far_m: Positive = 10.0  # farthest measured z


class TimeOfFlightConfig(Strict):
    """A Kinect v2 / Azure Kinect-like time-of-flight camera (sources in the module)."""

    noise_m: NonNegativeRange = (0.001, 0.002)  # axial noise sigma at 1 m
    noise_per_m: NonNegative = 0.001  # axial noise sigma added per metre of z
    flying_pixel_probability: FractionRange = (0.5, 1.0)  # share of edge pixels that mix both depths
    edge_jump_m: Positive = 0.02  # a z step above this across a pixel's neighbours is an edge
    range_m: PositiveRange = (0.5, 4.5)  # nearest and farthest measured z


class DepthSensorConfig(Strict):
    """The depth sensor behind the dataset's ``sensor_depth/`` maps, drawn per frame.

    ``models`` weighs the depth sensor models a frame is drawn from (``exact``, ``structured_light``,
    ``active_stereo``, ``time_of_flight``); ``misregistration_px`` is the depth-to-colour offset, drawn per
    frame in a random direction, applied to every model's output. The defaults, and why, are in
    docs/dataset.md.
    """

    models: dict[str, float] = Field(
        default_factory=lambda: {"active_stereo": 0.5, "structured_light": 0.3, "time_of_flight": 0.2}
    )  # weight of each model
    misregistration_px: NonNegativeRange = (0.0, 2.0)  # depth-to-colour offset magnitude
    structured_light: StructuredLightConfig = StructuredLightConfig()
    active_stereo: ActiveStereoConfig = ActiveStereoConfig()
    time_of_flight: TimeOfFlightConfig = TimeOfFlightConfig()

    @field_validator("models")
    @classmethod
    def _models(cls, v: dict[str, float]) -> dict[str, float]:
        return _weights(v, DEPTH_MODELS)


class SceneConfig(Strict):
    """The pipeline's ``scene`` section: the lighting kit, the material kit, surroundings, the colour
    camera's sensor effects and the depth sensor."""

    lighting: LightingConfig = LightingConfig()
    materials: MaterialsConfig = MaterialsConfig()
    surroundings: SurroundingsConfig = SurroundingsConfig()
    sensor: SensorConfig = SensorConfig()
    depth_sensor: DepthSensorConfig = DepthSensorConfig()


class CyclesConfig(Strict):
    """Blender Cycles settings, used when ``render.engine`` is ``cycles`` (the optional ``bpy`` package).

    Cycles path-traces on the CPU: ``samples`` per pixel at most (adaptive sampling stops earlier where a
    pixel's noise is below ``adaptive_threshold``), ``max_bounces`` of indirect light (diffuse and glossy
    each), OpenImageDenoise on the result when ``denoise``, ``threads`` render threads (0: every core).
    """

    samples: Annotated[int, Field(ge=1, le=4096)] = 32
    adaptive_threshold: Annotated[float, Field(gt=0.0, le=1.0)] = 0.05
    max_bounces: Annotated[int, Field(ge=0, le=32)] = 4
    denoise: bool = True
    threads: Annotated[int, Field(ge=0, le=1024)] = 0


class RenderConfig(Strict):
    """The pipeline's ``render`` section: how frames are rendered (not what is in them).

    ``engine`` picks the renderer of the RGB image: ``open3d`` (the project's own, Filament rasterised)
    or ``cycles`` (Blender's path tracer, settings in ``cycles``; for validation sets rendered by another
    renderer). Depth, instance ids and labels come from the same ray cast whichever engine is used.

    ``shadows: false`` turns every shadow off whatever the scene draws (about 0.05-0.1 s a frame less on
    a CPU). ``post_processing`` turns on Open3D's own tone mapping and FXAA, which cost about 0.3 s a frame
    on llvmpipe; without it the renderer reads back the linear image and applies its own camera response.
    ``texture_size_px`` is the side of generated texture maps; ``cache_dir`` holds them between runs
    (default ``~/.cache/rebar-servo/textures``).

    Open3D 0.19 keeps every distinct texture it has uploaded until the process ends (about 1.9 MB per 512 px
    map, 7.5 MB at 1024 px): the scene config bounds how many distinct ones there can be (rebar looks,
    ground kinds and variants), and this size sets what each costs.
    """

    engine: Literal["open3d", "cycles"] = "open3d"
    cycles: CyclesConfig = CyclesConfig()
    shadows: bool = True
    post_processing: bool = False
    texture_size_px: Literal[256, 512, 1024, 2048] = 512
    cache_dir: Path | None = None

    @model_validator(mode="after")
    def _cache(self) -> RenderConfig:
        if self.cache_dir is not None and self.cache_dir.exists() and not self.cache_dir.is_dir():
            raise ValueError(f"cache_dir {str(self.cache_dir)!r} is a file; accepted: a folder")
        return self
