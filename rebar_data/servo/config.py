"""Typed servo suite configs (``eval/<suite>.yaml``). Unknown keys and bad values are one clear ConfigError.

A suite names its detector and frame source, the world (mesh placement, robot, camera mount), the
controllers' settings, and its episodes: listed ones (``episodes``) and/or randomized ones
(``random``). Every field has a default, so a suite holds only what it changes; the defaults are the
set-up described in the README's servo section.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, model_validator

from rebar_data.config import ConfigError, Fraction, NonNegative, Positive, Strict, Vec3, read_yaml, validate
from rebar_data.perception.inference.detector import Reading
from rebar_data.perception.inference.model_file import Runtime
from rebar_data.scene.config import Range, SceneConfig

Count = Annotated[int, Field(ge=1)]


class WorldConfig(Strict):
    """Where things are (world frame: z up, metres), after the paper's Webots set-up.

    ``mesh_translation_m`` / ``mesh_rotation_deg`` place the mesh frame (for the tunnel segment: the
    crown of its mid-surface, +z the outward normal); the default stands the segment upright, its convex
    face towards the robot. ``flange_from_camera_m`` and ``flange_from_tcp_m`` are the fixed hand-eye
    and tool offsets in the flange frame (axes parallel to the flange's, z along the tool).
    """

    mesh_config: str = "pipelines/paper-tunnel.yaml"
    mesh_translation_m: Vec3 = (0.96, -1.5, 1.35)
    mesh_rotation_deg: Vec3 = (90.0, 0.0, -90.0)
    robot_base_m: Vec3 = (-0.138, -1.35, 1.18)
    table_center_m: tuple[float, float] = (-0.5, -1.52)
    table_size_m: Vec3 = (1.0, 1.18, 1.18)
    flange_from_camera_m: Vec3 = (0.0, -0.08, 0.03)
    flange_from_tcp_m: Vec3 = (0.0, 0.0, 0.3)
    tool_mass_kg: NonNegative = 1.2
    control_period_s: Positive = 0.032
    physics_hz: Positive = 240.0
    home_joints_rad: tuple[float, float, float, float, float, float] | None = None


class RobotCameraConfig(Strict):
    """Kinect v1: 640x480 with square pixels; ``fov_x_deg`` sets fx = fy (57 deg gives 589.4 px). Its depth
    image comes from ``depth_sensor``, a model of :mod:`rebar_data.render.depth_sensor` at the middle of the
    dataset default's parameters (``rebar_data.scene.sample.nominal_depth_sensor``)."""

    fov_x_deg: Annotated[float, Field(gt=10, lt=150)] = 57.0
    depth_sensor: Literal["structured_light", "active_stereo", "time_of_flight", "exact"] = (
        "structured_light"  # the depth sensor model: Kinect v1-like structured light by default
    )
    depth_noise: bool = True  # the depth sensor's noise (off: its shadows, window, steps and range only)
    depth_window_px: Annotated[int, Field(ge=1, le=31)] = 5


class GainConfig(Strict):
    """ViSP's adaptive gain: ``(at_zero - at_infinity) exp(-slope_at_zero x / (at_zero - at_infinity)) + at_infinity``
    with x the infinity norm of the error (normalised image units for IBVS, metres for PBVS)."""

    at_zero: Positive
    at_infinity: Positive
    slope_at_zero: Positive

    @model_validator(mode="after")
    def _order(self) -> GainConfig:
        if self.at_infinity > self.at_zero:
            raise ValueError(
                f"at_infinity = {self.at_infinity} is above at_zero = {self.at_zero}; accepted: a gain that "
                "falls (or stays) as the error grows"
            )
        return self


class IbvsConfig(Strict):
    """Point feature to ``desired_px`` (default: the principal point), optionally with log-depth to ``desired_depth_m``."""

    gain: GainConfig = GainConfig(at_zero=12.0, at_infinity=4.0, slope_at_zero=60.0)
    desired_px: tuple[float, float] | None = None
    desired_depth_m: Positive = 0.55
    depth_feature: bool = True
    rotation: bool = False
    converge_px: Positive = 0.5


class PbvsConfig(Strict):
    """3D target point (camera frame) to ``desired_m`` through a numerically calibrated Jacobian."""

    gain: GainConfig = GainConfig(at_zero=12.0, at_infinity=5.0, slope_at_zero=150.0)
    desired_m: Vec3 = (0.0, 0.0, 0.55)
    converge_m: Positive = 0.001
    perturbation_rad: Positive = 0.002
    recalibrate_every: Count = 4


class MotionConfig(Strict):
    """Limits on the commanded motion (the UR5's own joint speed and position limits always hold)."""

    camera_speed_m_s: Positive = 0.3
    camera_rate_rad_s: Positive = 1.5
    joint_margin_rad: NonNegative = 0.05
    damping: NonNegative = 0.02
    orientation_gain: NonNegative = 2.0


class SafetyConfig(Strict):
    """Visit limits. ``settle_frames`` consecutive frames below the convergence bar, with the tracked
    point known to ``converge_sigma_px`` (1 sigma per axis), end a visit as converged. After
    ``max_blind_frames`` frames without a detection of the target the arm holds still until it is seen
    again; after ``max_lost_frames`` such frames the visit ends as ``lost``."""

    max_iterations: Count = 150
    max_blind_frames: Count = 8
    max_lost_frames: Count = 20
    divergence_factor: Positive = 2.5
    settle_frames: Count = 3
    converge_sigma_px: Positive = 0.3


class TrackerSettings(Strict):
    """The target tracker's settings, as :class:`rebar_data.servo.tracker.TargetTracker` takes them (its
    defaults are these); ``detection_sigma_px`` is the detector's pixel noise per axis (0.1 for the exact
    detector). The detector runs on every ``detect_every``-th frame; KLT and the arm's motion carry the
    targets in between."""

    detection_sigma_px: Positive = 0.1
    klt_sigma_px: Positive = 0.03
    klt_motion_fraction: NonNegative = 0.03
    detect_every: Count = 1
    gate_px: Positive = 25.0
    drift_px: Positive = 3.0
    window_px: Annotated[int, Field(ge=5, le=61)] = 21


class TargetsConfig(Strict):
    """How targets are chosen from the clustered detections of the first frames."""

    cluster_radius_px: Positive = 12.0
    row_tolerance_px: Positive = 30.0
    margin_px: NonNegative = 40.0
    acquire_frames: Count = 3
    min_score: Fraction = 0.3


class AlignConfig(Strict):
    """The tool square to the mat and its jaw across the crossing while it servos (:mod:`rebar_data.servo.alignment`):
    the camera turns (``gain`` per second on the measured turn, ``theta u``) so that its optical axis, parallel
    to the tool's, lies along the mat's inward normal measured from the depth image within ``radius_m`` of the
    crossing, and its x axis (the tool's jaw) on the bisector of the two bars, or ``jaw_to_bar_deg`` from a bar.
    Each frame's measurement enters a running estimate with weight ``smoothing``. A visit converges only with
    the measured tilt and jaw turn below ``converge_tilt_deg`` and ``converge_jaw_deg``.

    The point the visit servos on: the detector finds and tracks the crossing, and where the tracked detection
    and the meeting point of the two bars' lines fitted to the depth image disagree by more than
    ``line_switch_px`` for three frames running, the visit servos on the lines' meeting point from then on.
    0 (the default) takes the lines' point as soon as three frames resolved both bars; ``null`` keeps the
    detection always. On eval/tour-deck.yaml the visits that ended on the lines' point were 0.10-0.20 mm off,
    those on the detection 0.3-1.4 mm (docs/servo.md, "The crossing from the bars' lines")."""

    enabled: bool = True
    gain: Positive = 5.0
    jaw_to_bar_deg: Annotated[float, Field(gt=0, lt=90)] | None = None
    radius_m: Annotated[float, Field(ge=0.02, le=0.3)] = 0.07
    smoothing: Annotated[float, Field(gt=0, le=1)] = 0.3
    converge_tilt_deg: Positive = 0.5
    converge_jaw_deg: Positive = 2.0
    line_switch_px: NonNegative | None = 0.0


class TcpConfig(Strict):
    """The tie, after centring: the tool centre point moved over the crossing ``clearance_m`` out along the
    tool's axis, then along that axis to ``standoff_m`` short of the crossing (the gun's tie stand-off), held
    there ``dwell_s`` (the tie), and back out along the axis. Tool moves run at up to ``speed_m_s``; the
    first leg ends within ``waypoint_tolerance_m``, the approach within ``tolerance_m``."""

    approach: bool = True
    standoff_m: NonNegative = 0.0
    clearance_m: NonNegative = 0.05
    dwell_s: NonNegative = 1.0
    speed_m_s: Positive = 1.0
    gain: Positive = 16.0
    max_iterations: Count = 120
    tolerance_m: Positive = 0.0005
    waypoint_tolerance_m: Positive = 0.003


class FaultsConfig(Strict):
    drop_fraction: Fraction = 0.0
    pixel_noise_px: NonNegative = 0.0
    spurious_per_frame: NonNegative = 0.0


class RecordingConfig(Strict):
    """Rerun recordings: one ``.rrd`` per episode (``episodes``), the first only (``first``), or none."""

    rrd: Literal["episodes", "first", "none"] = "episodes"
    jpeg_quality: Annotated[int, Field(ge=10, le=100)] = 80
    depth: bool = True


class StartPose(Strict):
    """A start pose by what the camera looks at: a point of the mesh given as (axial, arc) distances from
    the crown in metres, the camera ``standoff_m`` from it along the mesh normal, then tilted about the
    camera's x and y axes and rolled about its optical axis."""

    look_at_m: tuple[float, float] = (0.0, 0.0)
    standoff_m: Positive = 0.6
    tilt_deg: tuple[float, float] = (0.0, 0.0)
    roll_deg: float = 0.0


class EpisodeSpec(Strict):
    mode: Literal["ibvs", "pbvs"]
    start: StartPose = StartPose()
    targets: Count = 4
    choice: Literal["nearest", "random"] = "nearest"


class RandomEpisodes(Strict):
    """``count`` episodes with start poses drawn uniformly from these ranges, modes taken in turn."""

    count: Count
    modes: list[Literal["ibvs", "pbvs"]] = Field(default_factory=lambda: ["ibvs", "pbvs"], min_length=1)
    targets: Count = 2
    choice: Literal["nearest", "random"] = "random"
    axial_m: Range = (-0.25, 0.25)
    arc_m: Range = (-0.15, 0.2)
    standoff_m: Range = (0.5, 0.7)
    tilt_deg: NonNegative = 6.0
    roll_deg: NonNegative = 10.0


class TourBase(Strict):
    """One base pose of a tour: the robot's base (with its table: a mobile base, or a carriage on a rail)
    moved by the offset between the element's surface points at (``axial_m``, ``arc_m``) and at the crown,
    its orientation kept."""

    axial_m: float = 0.0
    arc_m: float = 0.0


class TourConfig(Strict):
    """A tour (:mod:`rebar_data.servo.tour`): from each base pose in turn, the camera looks at the element
    ``standoff_m`` out from the surface point the base was moved by, and every crossing of the top mat it
    finds within the arm's reach is tied once, nearest first along the shortest path over those seen
    (a crossing found behind the front mat by more than ``front_band_m`` is on a lower mat and never a
    target; one that fails ``max_attempts`` visits from a base is left by that base, and tried again from
    a later one that reaches it). ``max_ties`` ends the whole tour early."""

    mode: Literal["ibvs", "pbvs"] = "ibvs"
    bases: list[TourBase] = Field(default_factory=lambda: [TourBase()], min_length=1)
    standoff_m: Positive = 0.6
    max_ties: Count | None = None
    max_attempts: Count = 2
    front_band_m: Positive = 0.04
    merge_radius_m: Positive = 0.03


class MapView(Strict):
    """One camera view of a servo map's cells: the camera ``standoff_m`` out along the normal at the cell's
    surface point (the map's), then tilted about its x and y axes and rolled about its optical axis."""

    tilt_deg: tuple[float, float] = (0.0, 0.0)
    roll_deg: float = 0.0


class MapConfig(Strict):
    """A servo map (``rebar servo map SUITE``, :mod:`rebar_data.servo.sweep`): one episode (``targets``
    crossings, the nearest the image centre first) per cell of modes x turns x views x an ``axial_steps`` x
    ``arc_steps`` grid of surface points spanning ``axial_m`` x ``arc_m`` (the start pose's look-at point).
    ``turns_deg`` turns the element about its own normal at the crown (its orientation in the work cell:
    0 is the suite's placement). ``base: follow`` moves the robot's base (with its table: a mobile base, as a
    tour's bases do) by the offset between the cell's surface point and the crown, its orientation kept, so
    that a map covers the whole element; ``fixed`` keeps it where the suite puts it, so that a map also shows
    the arm's reach. A cell the arm cannot reach from its base is recorded as unreachable."""

    modes: list[Literal["ibvs", "pbvs"]] = Field(default_factory=lambda: ["ibvs", "pbvs"], min_length=1)
    axial_m: Range = (-0.4, 0.4)
    arc_m: Range = (-0.4, 0.4)
    axial_steps: Count = 5
    arc_steps: Count = 5
    standoff_m: Positive = 0.6
    views: list[MapView] = Field(default_factory=lambda: [MapView()], min_length=1)
    turns_deg: list[float] = Field(default_factory=lambda: [0.0], min_length=1)
    base: Literal["follow", "fixed"] = "follow"
    targets: Count = 1

    @property
    def cells(self) -> int:
        return len(self.modes) * len(self.turns_deg) * len(self.views) * self.axial_steps * self.arc_steps


class SuiteConfig(Strict):
    name: str
    seed: Annotated[int, Field(ge=0)] = 0
    detector: Literal["shipped", "ground_truth"] = "shipped"
    detector_path: str | None = None
    # what runs the shipped detector's model files (rebar_data.perception.inference.model_file): auto is OpenVINO in
    # bfloat16 where the CPU has it, ONNX Runtime in float32 elsewhere; pin one to compare machines
    detector_runtime: Runtime = "auto"
    # how the shipped detector reads each frame (rebar_data.perception.inference.detector): single (the default) reads it
    # once; mirrored also reads its mirror image, as Detector.load does by default. The servo keeps the single
    # reading: the robot's frames come with depth, where the mirrored reading adds little (paper-tunnel test
    # recall at precision 0.99 0.990 against 0.993), and on eval/paper.yaml it moved the worst IBVS visit's
    # true lateral error from 0.97 mm to 1.01-1.07 mm (bar 1 mm; the same visit in every reading tried, the
    # others 0.5 mm or less); the servo README has the figures
    detector_reading: Reading = "single"
    # whether the shipped detector first takes what lies far behind the bars in front out of each frame, from
    # its depth image (rebar_data.perception.inference.image; off, as Detector.load has it). Measured with it on:
    # eval/paper.yaml worst true lateral error IBVS / PBVS 0.98 / 0.50 mm (0.97 / 0.24 without),
    # eval/paper-lower-mat.yaml 1.44 / 0.51 mm (1.80 / 1.51 without)
    detector_flatten_behind: bool = False
    frames: Literal["renderer", "raycast"] = "renderer"
    shadows: bool = False
    scene: SceneConfig = SceneConfig()
    faults: FaultsConfig = FaultsConfig()
    world: WorldConfig = WorldConfig()
    camera: RobotCameraConfig = RobotCameraConfig()
    ibvs: IbvsConfig = IbvsConfig()
    pbvs: PbvsConfig = PbvsConfig()
    motion: MotionConfig = MotionConfig()
    safety: SafetyConfig = SafetyConfig()
    tracker: TrackerSettings = TrackerSettings()
    targets: TargetsConfig = TargetsConfig()
    align: AlignConfig = AlignConfig()
    tcp: TcpConfig = TcpConfig()
    recording: RecordingConfig = RecordingConfig()
    episodes: list[EpisodeSpec] = Field(default_factory=list)
    random: RandomEpisodes | None = None
    tour: TourConfig | None = None
    map: MapConfig | None = None

    @model_validator(mode="after")
    def _has_episodes(self) -> SuiteConfig:
        if not self.episodes and self.random is None and self.tour is None and self.map is None:
            raise ValueError(
                "no episodes: accepted: a list under 'episodes', a 'random' section, a 'tour', a 'map' "
                "(for rebar servo map), or several"
            )
        if self.ibvs.rotation and self.align.enabled:
            raise ValueError(
                "ibvs.rotation = true turns the camera to centre the point and align.enabled turns it square "
                "to the mat; accepted: one of them (align: {enabled: false} with ibvs.rotation: true)"
            )
        return self


def load_suite(path: str | Path) -> SuiteConfig:
    """Read and check a suite file."""
    return validate(SuiteConfig, read_yaml(path), str(path))


def resolve_path(name: str, suite_path: str | Path | None) -> Path:
    """A path from a suite: as given (relative to the working folder), else beside the suite's parent folder.

    So ``pipelines/paper-tunnel.yaml`` in ``eval/ci.yaml`` works from the project root and elsewhere.
    """
    p = Path(name)
    if p.is_absolute() or p.exists() or suite_path is None:
        if not p.exists():
            raise ConfigError(f"world.mesh_config = {name!r}: no such file; accepted: a pipeline YAML path")
        return p
    alt = Path(suite_path).resolve().parent.parent / p
    if alt.exists():
        return alt
    raise ConfigError(f"world.mesh_config = {name!r}: no such file; accepted: a pipeline YAML path")
