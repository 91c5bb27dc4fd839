"""Rerun recordings of servo episodes: camera frames, detections, tracking, errors, joints and the 3D cell.

One ``.rrd`` per episode, written through its own ``rr.RecordingStream`` (no global recording), with a
blueprint that opens on: the work cell in 3D (mesh, robot, camera frustum and trajectory, target) on
the left; the camera image with detections, the tracked point and the desired point, the depth image,
the error curves and the joint states on the right; the events of the episode below.

Timelines: ``step`` (control steps) and ``sim_time`` (simulated seconds). The stream's batcher holds an
episode's rows until the file is closed (or ``BATCH_MAX_BYTES`` is pending), so each entity is written as
one chunk rather than one for every flush of the default 200 ms tick (40-60 times fewer chunks).
"""

from __future__ import annotations

import datetime as dt
import uuid
from pathlib import Path

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from scipy.spatial.transform import Rotation

from rebar_data.servo import ur5
from rebar_data.servo.camera import KINECT_RANGE_M
from rebar_data.servo.config import EpisodeSpec, SuiteConfig
from rebar_data.servo.context import ServoContext
from rebar_data.servo.frames import CameraFrame
from rebar_data.servo.recorder import Recorder
from rebar_data.servo.tracker import TrackState
from rebar_data.servo.world import ServoWorld

ERROR_SERIES = {
    "error_px": ((230, 80, 60), "image error (px)"),
    "true_error_px": ((60, 160, 90), "true image error (px)"),
    "error_mm": ((70, 110, 220), "error (mm)"),
    "true_lateral_error_mm": ((150, 90, 200), "true lateral error (mm)"),
    "tool_move_error_mm": ((200, 150, 40), "tool move error (mm)"),
    "ties": ((30, 30, 30), "ties made"),
    "gain": ((120, 120, 120), "gain (1/s)"),
}
DEPTH_METER = 1000.0  # depth PNG units per metre (uint16 millimetres)
# Colour scale of the depth view: from the Kinect's near limit to past the floor seen from the start poses
# (the scene spans about 0.53-1.32 m); beyond it the colours saturate.
DEPTH_RANGE_M = (KINECT_RANGE_M[0], 1.5)
# Pixels where the sensor reads no depth are drawn as their own layer over the depth view ("no reading", dark
# grey), as a depth camera's viewer shows them. Beside each bar they are the projector's shadow: the strip of
# ground the bar hides from the projector, f b (1/z_bar - 1/z_ground) wide (about 38 px for bars 0.6 m away and
# ground at 1.25 m: Kinect v1's 75 mm baseline), so a mat in front of flat ground shows a band of no reading
# beside every bar that runs across the baseline. docs/servo.md, "The depth view".
NO_READING_COLOR = (70, 70, 70)
BATCH_MAX_BYTES = 256 * 1024 * 1024  # pending bytes that flush the batcher before the end of an episode
TRACK_COLORS = {
    "detected": (40, 220, 90),
    "predicted": (250, 210, 40),
    "reseeded": (60, 170, 255),
    "lost": (255, 60, 60),
}


def blueprint() -> rrb.Blueprint:
    """The layout the recording opens on."""
    camera = rrb.Spatial2DView(
        origin="world/camera/image",
        contents=["$origin", "$origin/detections", "$origin/track", "$origin/desired", "$origin/prediction"],
        name="camera",
    )
    depth = rrb.Spatial2DView(
        origin="world/camera/image", contents=["$origin/depth", "$origin/no_reading"], name="depth"
    )
    errors = rrb.TimeSeriesView(
        origin="metrics", contents=["$origin/error_px", "$origin/true_error_px"], name="image error (px)"
    )
    metric = rrb.TimeSeriesView(
        origin="metrics",
        contents=["$origin/error_mm", "$origin/true_lateral_error_mm", "$origin/tool_move_error_mm"],
        name="error (mm)",
    )
    ties = rrb.TimeSeriesView(origin="metrics", contents=["$origin/ties"], name="ties made")
    joints = rrb.TimeSeriesView(origin="joints", name="joints (rad, rad/s)")
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(
                    origin="world",
                    name="work cell",
                    contents=[
                        "$origin/**",
                        "- $origin/camera/image/depth",
                        "- $origin/camera/image/no_reading",
                    ],
                ),
                rrb.TextLogView(origin="events", name="events"),
                row_shares=[4, 1],
            ),
            rrb.Vertical(
                rrb.Horizontal(camera, depth),
                rrb.Horizontal(errors, metric, ties),
                joints,
                row_shares=[3, 2, 2],
            ),
            column_shares=[1, 1],
        ),
        collapse_panels=True,
    )


class RerunRecorder(Recorder):
    """Streams one episode to an ``.rrd`` file."""

    def __init__(
        self, path: Path, ctx: ServoContext, *, title: str, jpeg_quality: int = 80, depth: bool = True
    ):
        self.ctx = ctx
        self.jpeg_quality = jpeg_quality
        self.depth = depth
        self.rec = rr.RecordingStream(
            "rebar_servo",
            recording_id=f"{title} {uuid.uuid4().hex[:8]}",
            batcher_config=rr.ChunkBatcherConfig(
                flush_tick=dt.timedelta(days=1), flush_num_bytes=BATCH_MAX_BYTES
            ),
        )
        self.rec.save(str(path), default_blueprint=blueprint())
        self._trajectory: list[np.ndarray] = []
        self._ties: list[np.ndarray] = []
        self._visit = -1
        self._static()
        self.event(0, title)  # temporal: a static TextLog on "events" would hide every later event

    # --- static content --------------------------------------------------------------------------
    def _static(self) -> None:
        rec, ctx = self.rec, self.ctx
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        m = ctx.rm.mesh
        rec.log(
            "world/mesh",
            rr.Mesh3D(
                vertex_positions=np.asarray(m.vertices, np.float32),
                triangle_indices=np.asarray(m.faces, np.uint32),
                albedo_factor=(150, 95, 62),
            ),
            static=True,
        )
        rec.log(
            "world/crossings",
            rr.Points3D(ctx.rm.crossings.point, radii=0.003, colors=(255, 60, 60)),
            static=True,
        )
        w = ctx.world.cfg
        size = np.array(w.table_size_m)
        rec.log(
            "world/table",
            rr.Boxes3D(
                centers=[[*w.table_center_m, size[2] / 2]],
                half_sizes=[size / 2],
                colors=(140, 110, 80),
                fill_mode="solid",
            ),
            static=True,
        )
        rec.log(
            "world/floor",
            rr.Boxes3D(
                centers=[[0.0, -1.5, -0.005]],
                half_sizes=[[2.0, 2.5, 0.005]],
                colors=(90, 90, 95),
                fill_mode="solid",
            ),
            static=True,
        )
        for i, shapes in enumerate(ur5.link_shapes()):
            self._log_cylinders(
                f"world/robot/link_{i}", shapes, (160, 180, 200) if i % 2 else (200, 200, 205)
            )
        tool_len = float(ctx.world.layout.flange_from_tcp[2, 3])
        self._log_cylinders(
            "world/robot/tool", [((0, 0, tool_len / 2), (0, 0, 0), 0.02, tool_len)], (230, 130, 30)
        )
        rec.log(
            "world/camera/image/no_reading",
            rr.AnnotationContext([rr.AnnotationInfo(id=1, label="no reading", color=NO_READING_COLOR)]),
            static=True,
        )
        cam = ctx.camera
        rec.log(
            "world/camera/image",
            rr.Pinhole(
                image_from_camera=cam.K, resolution=[cam.width, cam.height], image_plane_distance=0.15
            ),
            static=True,
        )
        for name, (color, label) in ERROR_SERIES.items():
            rec.log(f"metrics/{name}", rr.SeriesLines(colors=[color], names=[label]), static=True)
        for j, name in enumerate(ur5.JOINT_NAMES):
            rec.log(f"joints/q/{name}", rr.SeriesLines(names=[f"q {name}"], widths=[1.5]), static=True)
            rec.log(f"joints/qdot/{name}", rr.SeriesLines(names=[f"qdot {name}"], widths=[1.0]), static=True)
            del j

    def _log_cylinders(self, path: str, shapes, color) -> None:
        quats = [Rotation.from_euler("xyz", rpy).as_quat() for _, rpy, _, _ in shapes]
        self.rec.log(
            path,
            rr.Cylinders3D(
                lengths=[s[3] for s in shapes],
                radii=[s[2] for s in shapes],
                centers=[s[0] for s in shapes],
                quaternions=[rr.Quaternion(xyzw=q) for q in quats],
                colors=[color],
                fill_mode="solid",
            ),
            static=True,
        )

    # --- per step --------------------------------------------------------------------------------
    def _time(self, step: int) -> None:
        self.rec.set_time("step", sequence=step)
        self.rec.set_time("sim_time", duration=step * self.ctx.world.cfg.control_period_s)

    def frame(
        self,
        step: int,
        frame: CameraFrame,
        detections: np.ndarray,
        *,
        track: TrackState | None = None,
        desired: np.ndarray | None = None,
        prediction: np.ndarray | None = None,
    ) -> None:
        rec = self.rec
        self._time(step)
        ok, jpg = cv2.imencode(".jpg", frame.rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if ok:
            rec.log("world/camera/image", rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg"))
        if self.depth:
            valid = frame.depth_m > 0
            rec.log(
                "world/camera/image/no_reading", rr.SegmentationImage((~valid).astype(np.uint8), opacity=1.0)
            )
            mm = np.clip(np.round(frame.depth_m * DEPTH_METER), 0, 65535).astype(np.uint16)
            ok, png = cv2.imencode(".png", mm)
            if ok:
                rec.log(
                    "world/camera/image/depth",
                    rr.EncodedDepthImage(
                        png.tobytes(),
                        media_type="image/png",
                        meter=DEPTH_METER,
                        depth_range=[x * DEPTH_METER for x in DEPTH_RANGE_M],  # in the image's units
                        colormap="turbo",
                    ),
                )
        det = np.asarray(detections, float).reshape(-1, 3)
        rec.log(
            "world/camera/image/detections",
            rr.Points2D(
                det[:, :2],
                radii=4.0,
                colors=(255, 255, 255),
                labels=[f"{s:.2f}" for s in det[:, 2]],
                show_labels=False,
            ),
        )
        if track is not None:
            rec.log(
                "world/camera/image/track",
                rr.Points2D(
                    [track.point],
                    radii=6.0,
                    colors=TRACK_COLORS.get(track.source, (255, 255, 255)),
                    labels=[track.source],
                ),
            )
        else:
            rec.log("world/camera/image/track", rr.Clear(recursive=False))
        if desired is not None:
            d = np.asarray(desired, float)
            rec.log(
                "world/camera/image/desired",
                rr.LineStrips2D(
                    [[d - [12, 0], d + [12, 0]], [d - [0, 12], d + [0, 12]]], colors=(255, 80, 220), radii=1.0
                ),
            )
        if prediction is not None and np.all(np.isfinite(prediction)):
            rec.log(
                "world/camera/image/prediction", rr.Points2D([prediction], radii=8.0, colors=(255, 140, 0))
            )

    def state(
        self,
        step: int,
        world: ServoWorld,
        *,
        twist: np.ndarray | None = None,
        visit: int | None = None,
        target_world: np.ndarray | None = None,
    ) -> None:
        rec = self.rec
        self._time(step)
        poses = world.link_poses()
        for i, T in enumerate(poses):
            rec.log(f"world/robot/link_{i}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        F = world.world_from_link(6)
        rec.log("world/robot/tool", rr.Transform3D(translation=F[:3, 3], mat3x3=F[:3, :3]))
        C = world.world_from_camera()
        rec.log("world/camera", rr.Transform3D(translation=C[:3, 3], mat3x3=C[:3, :3]))
        tcp = world.world_from_tcp()[:3, 3]
        rec.log("world/tcp", rr.Points3D([tcp], radii=0.006, colors=(255, 150, 0)))
        self._trajectory.append(C[:3, 3].copy())
        rec.log(
            "world/trajectory/camera",
            rr.LineStrips3D([np.array(self._trajectory)], colors=(80, 200, 255), radii=0.002),
        )
        q, qd = world.q, world.qdot
        for j, name in enumerate(ur5.JOINT_NAMES):
            rec.log(f"joints/q/{name}", rr.Scalars(q[j]))
            rec.log(f"joints/qdot/{name}", rr.Scalars(qd[j]))

    def target(self, step: int, point_world: np.ndarray, label: str) -> None:
        self._time(step)
        self.rec.log(
            "world/target", rr.Points3D([point_world], radii=0.008, colors=(255, 0, 200), labels=[label])
        )

    def tie(self, step: int, point_world: np.ndarray, axis_world: np.ndarray, row) -> None:
        """A tie as it is made: every tie so far, the running count, and the tool's axis (orange) against the
        mat's true inward normal (green) at the crossing."""
        self._time(step)
        self._ties.append(np.asarray(point_world, float))
        n = len(self._ties)
        self.rec.log(
            "world/ties",
            rr.Points3D(
                np.array(self._ties),
                radii=0.006,
                colors=(40, 200, 255),
                labels=[str(i + 1) for i in range(n)],
            ),
        )
        arrows = [np.asarray(axis_world, float) * -0.12]
        colors = [(230, 130, 30)]
        if row.target_id >= 0:
            arrows.append(self.ctx.truth.normal[row.target_id] * 0.12)
            colors.append((60, 200, 90))
        self.rec.log(
            "world/ties/axis",
            rr.Arrows3D(origins=[point_world] * len(arrows), vectors=arrows, colors=colors, radii=0.002),
        )
        self.rec.log("metrics/ties", rr.Scalars(float(n)))
        self.event(
            step,
            f"tie {n}: crossing {row.target_id}, tool {row.tcp_lateral_error_m * 1000:.2f} mm off, axis "
            f"{row.tie_tilt_error_deg:.2f} deg from the normal, jaw {row.tie_jaw_error_deg:.2f} deg from the bisector",
        )

    def scalars(self, step: int, values: dict[str, float]) -> None:
        self._time(step)
        for name, value in values.items():
            if value is not None and np.isfinite(value):
                self.rec.log(f"metrics/{name}", rr.Scalars(float(value)))

    def scalars_gap(self, step: int) -> None:
        """End the error curves of a visit, so the next visit's curves do not join them."""
        self._time(step)
        for name in ERROR_SERIES:
            if name != "ties":  # the running count runs on across visits
                self.rec.log(f"metrics/{name}", rr.Clear(recursive=False))

    def event(self, step: int, text: str) -> None:
        self._time(step)
        self.rec.log("events", rr.TextLog(text, level=rr.TextLogLevel.INFO))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()


def recorder_for(
    suite: SuiteConfig, ctx: ServoContext, out: Path, k: int, index: int, spec: EpisodeSpec
) -> Recorder | None:
    """The recorder of the k-th episode run, or None when the suite records no file for it."""
    mode = suite.recording.rrd
    if mode == "none" or (mode == "first" and k > 0):
        return None
    path = out / f"episode_{k:03d}_{spec.mode}.rrd"
    title = f"{suite.name} episode {index} ({spec.mode})"
    return RerunRecorder(
        path, ctx, title=title, jpeg_quality=suite.recording.jpeg_quality, depth=suite.recording.depth
    )
