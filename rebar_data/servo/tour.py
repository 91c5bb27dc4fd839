"""A tour: every crossing of the top mat within the arm's reach tied once, from each base pose in turn.

From each base pose (:class:`~rebar_data.servo.config.TourBase`, one episode each) the camera first looks at
the element and every crossing it detects goes into the tour's map of crossings (world points, by the
controller's own camera pose estimate and the depth image; one map for the whole tour, so a crossing tied
from one base is never tied again from the next). Then, until no open crossing is left in reach:

- the open crossings the arm can reach (its servo pose and its tie pose both solved by the UR5's inverse
  kinematics within the joint limits, the elbow neither stretched nor folded nor bent the other way than
  it is, every link 20 mm clear of the
  mesh and the table) are ordered along the shortest open path from where the camera looks
  (nearest neighbour, then 2-opt), and the first is the next target;
- the target is picked up in the present frame on the detection nearest where the map projects it (none
  within the cluster radius: not picked up), and tracked from there: no fresh acquisition;
- the visit servos onto it, squares the tool and ties (:func:`rebar_data.servo.control.visit`);
- the frame the camera sees back at its view pose adds the crossings newly in view.

A detection lying more than ``front_band_m`` behind the front mat around it (the depth image's nearest
surface there) is on a lower mat: it enters the map as such and is never a target. A target where the servo
never resolved two bars on the front mat (a top bar passing over a lower one, a spurious detection) ends its
visit as ``no_crossing``, untied, and is never a target again. A target not tied in ``max_attempts`` visits
from one base (or in one, where the tool did not reach its tie pose: the arm at its reach) is left by that
base and stays in the map as failed; a later base that reaches it tries it again from its own pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rebar_data.camera import rigid_inverse
from rebar_data.servo import control
from rebar_data.servo.config import EpisodeSpec, StartPose, TourConfig
from rebar_data.servo.episode import EpisodeRunner
from rebar_data.servo.sensing import Target
from rebar_data.servo.targets import persistent_clusters
from rebar_data.servo.tracker import TargetTracker
from rebar_data.servo.transforms import apply, make_transform

OPEN, TIED, FAILED, LOWER, NOT_CROSSING = "open", "tied", "failed", "lower_mat", "not_a_crossing"
FRONT_WINDOW_M = 0.05  # the front mat around a detection: the nearest surface within this radius
# the elbow's working range for a target's servo and tie poses (|q|, rad): stretched, the arm is at its reach,
# where the damped control stalls short of it; folded, the forearm turns over the upper arm
ELBOW_MIN_RAD = 0.35
ELBOW_MAX_RAD = np.pi - 0.6


@dataclass
class MapEntry:
    point: np.ndarray  # world, by the controller's pose estimate (a running mean over sightings)
    sightings: int
    state: str = OPEN
    attempts: int = 0  # visits that did not tie, from every base
    here: int = 0  # of those, from the present base
    left_by: frozenset[int] = frozenset()  # the bases that left it

    def failed(self, base: int, max_attempts: int, *, out_of_reach: bool = False) -> None:
        """One attempt from ``base`` that did not tie. After ``max_attempts`` from one base (or at once, where
        the tool did not reach its tie pose: the arm's reach from there, which another try does not change)
        this base leaves it, ``FAILED`` until another base ties it."""
        self.attempts += 1
        self.here += 1
        if out_of_reach or self.here >= max_attempts:
            self.state = FAILED
            self.left_by = self.left_by | {base}

    def open_to(self, base: int) -> bool:
        """Whether ``base`` may visit it: open, or failed only from other bases (a new base sees it anew)."""
        return self.state == OPEN or (self.state == FAILED and base not in self.left_by)


class CrossingMap:
    """The crossings a tour has seen, in the world frame; detections within ``merge_radius_m`` of an entry
    are the same crossing."""

    def __init__(self, merge_radius_m: float):
        self.merge_radius_m = merge_radius_m
        self.entries: list[MapEntry] = []

    def add(self, point: np.ndarray, *, lower: bool) -> MapEntry:
        for e in self.entries:
            if np.linalg.norm(e.point - point) < self.merge_radius_m:
                if e.state in (OPEN, LOWER):
                    e.point = (e.point * e.sightings + point) / (e.sightings + 1)
                    e.sightings += 1
                return e
        e = MapEntry(point=np.array(point, float), sightings=1, state=LOWER if lower else OPEN)
        self.entries.append(e)
        return e

    def count(self, state: str) -> int:
        return sum(e.state == state for e in self.entries)


def open_path(start: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The order of ``points`` along a short open path from ``start``: nearest neighbour, then 2-opt."""
    n = len(points)
    if n <= 1:
        return np.arange(n)
    left = list(range(n))
    order: list[int] = []
    here = start
    while left:
        j = min(left, key=lambda i: float(np.linalg.norm(points[i] - here)))
        order.append(j)
        left.remove(j)
        here = points[j]
    path = np.vstack([start[None], points[order]])
    D = np.linalg.norm(path[:, None, :] - path[None, :, :], axis=2)  # every pair's distance, once
    idx = list(range(n + 1))

    def d(a: int, b: int) -> float:
        return float(D[a, b])

    improved = True
    while improved:
        improved = False
        for i in range(1, n):
            for k in range(i + 1, n + 1):
                a, b = idx[i - 1], idx[i]
                c = idx[k]
                after = idx[k + 1] if k < n else None
                old = d(a, b) + (d(c, after) if after is not None else 0.0)
                new = d(a, c) + (d(b, after) if after is not None else 0.0)
                if new < old - 1e-9:
                    idx[i : k + 1] = idx[i : k + 1][::-1]
                    improved = True
    return np.array([order[i - 1] for i in idx[1:]])


class TourRunner(EpisodeRunner):
    """One base pose of a tour: an episode whose visits are every open crossing in reach, shared map."""

    def __init__(
        self,
        ctx,
        tour: TourConfig,
        index: int,
        seed_seq,
        recorder=None,
        *,
        snapshots=False,
        crossing_map: CrossingMap,
        ties_left: int | None,
    ):
        spec = EpisodeSpec(mode=tour.mode, targets=1)
        super().__init__(ctx, spec, index, seed_seq, recorder, snapshots=snapshots)
        self.tour, self.map, self.ties_left = tour, crossing_map, ties_left
        self._reach: dict[int, bool] = {}

    def run_base(self, start: StartPose, q_start: np.ndarray) -> None:
        """Survey from the start pose, then visit every open crossing in reach (fills ``self.result``)."""
        self.begin(start, q_start)
        for e in self.map.entries:
            e.here = 0
        self.rec.event(self.step_index, f"tour base {self.index}: look at {start.look_at_m}")
        last = self.survey(frames=self.ctx.suite.targets.acquire_frames)
        while self.ties_left is None or self.ties_left > 0:
            entry = self.next_entry()
            if entry is None:
                break
            k = len(self.result.visits)
            target = self.pick_up(entry, last)
            if target is None:  # out of view: look at where the map has it, then pick it up
                last = self.look_at(entry, k)
                target = self.pick_up(entry, last)
            if target is None:
                entry.failed(self.index, self.tour.max_attempts)
                continue
            self.pending = [target]
            control.visit(self, k, target)
            row = self.result.visits[-1]
            if row.reason == "no_crossing":  # no two bars on the front mat there: never a target again
                entry.state = NOT_CROSSING
            elif row.tied:
                entry.state = TIED
                if self.ties_left is not None:
                    self.ties_left -= 1
            else:
                entry.failed(self.index, self.tour.max_attempts, out_of_reach=row.converged and not row.tcp_reached)
            self.rec.event(
                self.step_index,
                f"ties {sum(v.tied for v in self.result.visits)} from this base, {self.map.count(TIED)} in all",
            )
            last = self.survey(frames=1)

    # --- the map ---------------------------------------------------------------------------------
    def survey(self, frames: int):
        """Detections over a few frames of the still arm into the map; the last sensed frame."""
        dets, s = self.still_frames(frames)
        clusters = persistent_clusters(dets, self.ctx.suite.targets.cluster_radius_px)
        pose = self.controller.camera_pose()
        for uv in clusters.center:
            z = self.sensing.crossing_depth(s.frame, uv)
            if not np.isfinite(z):
                continue
            p_cam = self.ctx.camera.back_project(uv[None], np.array([z]))[0]
            self.map.add(apply(pose, p_cam), lower=self._behind_front(s.frame.depth_m, uv, z))
        return s

    def _behind_front(self, depth_m: np.ndarray, uv: np.ndarray, z: float) -> bool:
        """Whether a crossing at pixel ``uv`` and depth ``z`` lies behind the front mat around it."""
        cam = self.ctx.camera
        r = int(np.ceil(FRONT_WINDOW_M * cam.fx / z))
        h, w = depth_m.shape
        u, v = int(round(float(uv[0]))), int(round(float(uv[1])))
        patch = depth_m[max(v - r, 0) : min(v + r + 1, h), max(u - r, 0) : min(u + r + 1, w)]
        vals = patch[patch > 0]
        if vals.size < 20:
            return False
        front = float(np.percentile(vals, 5)) + self.ctx.depth_offset_m
        return z - front > self.tour.front_band_m

    # --- the next target ---------------------------------------------------------------------------
    def next_entry(self) -> MapEntry | None:
        pose = self.controller.camera_pose()
        here = pose[:3, 3] + pose[:3, 2] * self.ctx.suite.ibvs.desired_depth_m
        cands = [(i, e) for i, e in enumerate(self.map.entries) if e.open_to(self.index) and self._reachable(i, e)]
        if not cands:
            return None
        order = open_path(here, np.array([e.point for _, e in cands]))
        return cands[int(order[0])][1]

    def _reachable(self, i: int, e: MapEntry) -> bool:
        """Whether the arm reaches the entry's servo pose and tie pose (solved once per entry and base)."""
        if i in self._reach:
            return self._reach[i]
        world = self.ctx.world
        R = self.controller.camera_pose()[:3, :3]  # the present orientation: the mat's within a few degrees
        view = make_transform(R, e.point - R[:, 2] * self.ctx.suite.ibvs.desired_depth_m)
        camera_from_tcp = world.layout.camera_from_tcp
        tie = make_transform(R, e.point - R @ camera_from_tcp[:3, 3])
        ok = True
        for T in (view, tie):
            q, solved = world.solve_start(T, seed=world.q)
            # the elbow bent the way it is now: the arm moves there continuously, and an elbow bent the other
            # way is a pose it reaches only through the stretched arm, past its reach
            same_bend = np.sign(q[2]) == np.sign(world.q[2])
            ok = ok and solved and same_bend and ELBOW_MIN_RAD <= abs(float(q[2])) <= ELBOW_MAX_RAD
            ok = ok and world.clear_at(q)
        self._reach[i] = ok
        return ok

    def look_at(self, entry: MapEntry, k: int):
        """Move the camera (on its pose estimate, orientation held) to view the entry along its optical axis
        from the servo's standoff; survey there. The move's rows are phase ``transfer`` of visit ``k``."""
        pose = self.controller.camera_pose()
        view = make_transform(pose[:3, :3], entry.point - pose[:3, 2] * self.ctx.suite.ibvs.desired_depth_m)
        cfg = self.ctx.suite.tcp
        control.move_camera_to(
            self,
            k,
            view,
            phase="transfer",
            max_iterations=cfg.max_iterations,
            tol=0.005,
            speed_m_s=cfg.speed_m_s,
            gain=cfg.gain,
        )
        return self.survey(frames=1)

    def pick_up(self, entry: MapEntry, sensed) -> Target | None:
        """The entry as a tracked target in the present frame, on the detection nearest where the map projects
        it (None where it projects outside the frame or no detection lies within the cluster radius)."""
        cam = self.ctx.camera
        pose = self.controller.camera_pose()
        p = apply(rigid_inverse(pose), entry.point)
        if p[2] <= 0:
            return None
        uv = cam.project(p)[0]
        margin = 10.0
        if not (margin <= uv[0] <= cam.width - margin and margin <= uv[1] <= cam.height - margin):
            return None
        det = sensed.detections
        sigma = self.ctx.suite.tracker.detection_sigma_px
        if not len(det):
            return None
        d = np.linalg.norm(det[:, :2] - uv, axis=1)
        j = int(np.argmin(d))
        if d[j] > self.ctx.suite.targets.cluster_radius_px:
            return (
                None  # not seen where the map has it: a target is picked up on a detection, never on a guess
            )
        uv = det[j, :2]
        tracker = TargetTracker(self.ctx.suite.tracker)
        tracker.seed(sensed.frame.rgb, uv, sigma)
        t = Target(
            uv=uv,
            crossing_id=self.sensing.true_crossing(uv, self.ctx.world.world_from_camera()),
            tracker=tracker,
            pose=pose,
        )
        z = self.sensing.crossing_depth(sensed.frame, uv)
        t.depth_m = z if np.isfinite(z) else float(p[2])
        return t


def tour_summary(
    visits: list[dict], steps: list[dict], crossing_map: CrossingMap, crossings_total: int
) -> dict:
    """A tour's figures: ties, what the map held, the simulated time a tie (each base's whole clock: the
    survey, the moves between targets and every visit), and the element covered."""
    ties = [v for v in visits if v["tied"]]
    tied_ids = {v["target_id"] for v in ties if v["target_id"] >= 0}
    clock: dict[int, float] = {}
    for st in steps:
        clock[st["episode"]] = max(clock.get(st["episode"], 0.0), st["time_s"])
    sim_s = float(sum(clock.values()))
    return {
        "ties": len(ties),
        "visits": len(visits),
        "crossings_tied": len(tied_ids),
        "crossings_in_element": crossings_total,
        "covered_fraction": len(tied_ids) / crossings_total if crossings_total else 0.0,
        "map": {state: crossing_map.count(state) for state in (OPEN, TIED, FAILED, LOWER, NOT_CROSSING)},
        "tied_fraction": len(ties) / (len(ties) + crossing_map.count(FAILED)) if ties else 0.0,
        "ties_off_crossings": sum(1 for v in ties if not v["tie_crossing_distance_m"] <= 0.005),
        "sim_s": sim_s,
        "sim_s_per_tie": sim_s / len(ties) if ties else float("nan"),
        "ties_per_hour": 3600.0 * len(ties) / sim_s if sim_s > 0 else 0.0,
    }
