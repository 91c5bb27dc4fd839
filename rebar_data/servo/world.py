"""The simulated work cell: floor, table, UR5 with an eye-in-hand camera and tying tool, the rebar mesh.

pybullet runs in DIRECT mode through one :class:`BulletClient`; physics steps at ``physics_hz`` and the
controller at ``control_period_s`` (32 ms, 31 Hz, as the paper). 32 ms is 7.68 physics steps at 240 Hz,
so each control period runs the 7 or 8 steps that bring the physics clock to the next control tick:
the control clock never drifts from the 32 ms grid. Joints are driven by velocity commands through
pybullet's velocity motors, with the UR5's torque limits as the motor forces.

Layout (world z up, metres). Read with the table's position as its centre, the paper's set-up leaves
its UR5 at (-0.138, -1.35, 1.18) 0.17 m beyond the table's edge; read as the table's (+x, -y) corner
it stands the robot on the table, 0.138 m from the edge that faces the mesh, so we read it that way:
the table spans x in [-1.0, 0.0] and y in [-2.11, -0.93]. The
paper's mesh at (2.8, -1.5, 2.61) is 2.9 m from the robot, out of its 0.85 m reach. We stand the tunnel
segment upright with its convex face towards the robot (tunnel axis horizontal along y, arc vertical;
the paper gives it as 3.02 m wide and 2.4 m high), keep the paper's y = -1.5, and bring its crown to 1.1 m in front of
the robot base at 1.35 m height (0.17 m above the table). Then the camera can look at the crossings in
front of the robot from 0.5-0.65 m in well-conditioned arm poses (smallest Jacobian singular value
above 0.08, elbow and wrist up, every link above the table), and the 0.3 m tying tool reaches the same
crossings without the arm changing configuration.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from rebar_data.camera import rigid_inverse
from rebar_data.config import ConfigError
from rebar_data.geometry.build import RebarMesh, build_rebar_mesh
from rebar_data.geometry.config import Pose
from rebar_data.pipeline import load_mesh_config
from rebar_data.scene.mat_surface import MatSurface
from rebar_data.servo import ur5
from rebar_data.servo.client import BulletClient, quiet_stdout
from rebar_data.servo.config import StartPose, WorldConfig
from rebar_data.servo.transforms import apply, make_transform, translation

FLANGE_LINK, CAMERA_LINK, TCP_LINK = 6, 7, 8


def build_world_mesh(world: WorldConfig, mesh_config_path: Path) -> RebarMesh:
    """The rebar mesh of ``mesh_config_path`` placed by the world's pose (its own pose is replaced)."""
    cfg = load_mesh_config(mesh_config_path)
    pose = Pose(translation_m=world.mesh_translation_m, rotation_deg=world.mesh_rotation_deg)
    return build_rebar_mesh(cfg.model_copy(update={"pose": pose}))


@dataclass(frozen=True)
class Layout:
    """Fixed transforms of the cell."""

    world_from_base: np.ndarray
    flange_from_camera: np.ndarray
    flange_from_tcp: np.ndarray

    @cached_property
    def camera_from_tcp(self) -> np.ndarray:
        return rigid_inverse(self.flange_from_camera) @ self.flange_from_tcp

    @staticmethod
    def of(world: WorldConfig) -> Layout:
        return Layout(
            translation(world.robot_base_m),
            translation(world.flange_from_camera_m),
            translation(world.flange_from_tcp_m),
        )


class ServoWorld:
    """The pybullet cell and the robot's sensors: joint states, true link poses, the simulated clock."""

    def __init__(self, cfg: WorldConfig, rm: RebarMesh) -> None:
        self.cfg, self.rm = cfg, rm
        self.layout = Layout.of(cfg)
        self.limits = ur5.JointLimits.ur5()
        self.client = BulletClient()
        c = self.client
        c.setGravity(0, 0, -9.81)
        c.setTimeStep(1.0 / cfg.physics_hz)
        self.floor = c.createMultiBody(0, c.createCollisionShape(c.GEOM_PLANE))
        half = np.array(cfg.table_size_m) / 2
        tx, ty = cfg.table_center_m
        table_shape = c.createCollisionShape(c.GEOM_BOX, halfExtents=half.tolist())
        self.table = c.createMultiBody(0, table_shape, basePosition=[tx, ty, half[2]])
        self.robot = self._load_robot()
        for link in (-1, 0):  # the base and the shoulder sit on the table: mounted, not in contact
            c.setCollisionFilterPair(self.robot, self.table, link, -1, enableCollision=0)
        self.mesh_body = self._load_mesh()
        self._loaded_at = {b: c.getBasePositionAndOrientation(b) for b in (self.robot, self.table)}
        self.physics_steps = 0
        self.control_steps = 0

    def _load_robot(self) -> int:
        c = self.layout
        urdf = ur5.ur5_urdf(
            extra_links={"camera": c.flange_from_camera, "tcp": c.flange_from_tcp},
            tool_length_m=float(c.flange_from_tcp[2, 3]),
            tool_mass_kg=self.cfg.tool_mass_kg,
            tool_collision=False,
        )
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "ur5.urdf"
            path.write_text(urdf)
            with quiet_stdout():
                body = self.client.loadURDF(
                    str(path),
                    basePosition=list(self.cfg.robot_base_m),
                    useFixedBase=True,
                    flags=self.client.URDF_USE_INERTIA_FROM_FILE,
                )
        for j in range(6):
            self.client.changeDynamics(body, j, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0)
        return body

    def _load_mesh(self) -> int:
        c = self.client
        m = self.rm.mesh
        shape = c.createCollisionShape(
            c.GEOM_MESH,
            vertices=np.asarray(m.vertices).tolist(),
            indices=np.asarray(m.faces).reshape(-1).tolist(),
            flags=c.GEOM_FORCE_CONCAVE_TRIMESH,
        )
        return c.createMultiBody(0, shape)

    def close(self) -> None:
        self.client.close()

    # --- state -------------------------------------------------------------------------------
    @property
    def q(self) -> np.ndarray:
        return np.array([s[0] for s in self.client.getJointStates(self.robot, range(6))])

    @property
    def qdot(self) -> np.ndarray:
        return np.array([s[1] for s in self.client.getJointStates(self.robot, range(6))])

    @property
    def time_s(self) -> float:
        return self.control_steps * self.cfg.control_period_s

    def reset_clock(self) -> None:
        """Start the simulated clock again at 0 (each episode runs on its own clock)."""
        self.physics_steps = 0
        self.control_steps = 0

    def move_base(self, offset_m: np.ndarray) -> None:
        """Put the robot's base, with its table (a mobile base or a carriage on a rail), ``offset_m`` from
        where the world config places it (tours only; the arm keeps its joints)."""
        offset = np.asarray(offset_m, float)
        c = self.client
        # pybullet places a body by its base's inertial frame: move each from where it was loaded
        for body, (at, turn) in self._loaded_at.items():
            c.resetBasePositionAndOrientation(body, (np.array(at) + offset).tolist(), turn)
        self.layout = replace(
            self.layout, world_from_base=translation(np.array(self.cfg.robot_base_m) + offset)
        )

    def reset_joints(self, q: np.ndarray) -> None:
        """Teleport the arm to ``q`` at rest and hold it there (episode set-up only)."""
        for j in range(6):
            self.client.resetJointState(self.robot, j, float(q[j]), 0.0)
        self.command(np.zeros(6))

    def world_from_link(self, link: int) -> np.ndarray:
        """The simulator's true pose of a link frame (the ground truth, and the robot's pose measurement)."""
        s = self.client.getLinkState(self.robot, link, computeForwardKinematics=True)
        R = np.array(self.client.getMatrixFromQuaternion(s[5])).reshape(3, 3)
        return make_transform(R, np.array(s[4]))

    def world_from_camera(self) -> np.ndarray:
        return self.world_from_link(CAMERA_LINK)

    def world_from_tcp(self) -> np.ndarray:
        return self.world_from_link(TCP_LINK)

    def link_poses(self) -> list[np.ndarray]:
        """World poses of the base and the six moving links (URDF link frames), for recordings."""
        return [self.layout.world_from_base] + [self.world_from_link(j) for j in range(6)]

    def in_contact(self) -> bool:
        """Whether an arm link touches the mesh, the table (the base on the table does not count) or the
        floor (a base moved down on its lift, or a low start, can put the arm's links into it)."""
        c = self.client
        if c.getContactPoints(bodyA=self.robot, bodyB=self.mesh_body):
            return True
        if any(p[3] > 0 for p in c.getContactPoints(bodyA=self.robot, bodyB=self.floor)):
            return True
        return bool(c.getContactPoints(bodyA=self.robot, bodyB=self.table))

    # --- motion ------------------------------------------------------------------------------
    def command(self, qdot: np.ndarray) -> np.ndarray:
        """Joint velocity command for the next control period, clipped to the joint speed limits and so
        that no joint can pass its position limit: a joint may cover at most half of its remaining range
        in a period, so it slows down geometrically towards a limit and its motor's lag cannot carry it
        over. Returns what was sent."""
        dt = self.cfg.control_period_s
        q = self.q
        qd = np.clip(np.asarray(qdot, float), -self.limits.speed, self.limits.speed)
        lo = np.minimum((self.limits.lower - q) / (2 * dt), 0.0)
        hi = np.maximum((self.limits.upper - q) / (2 * dt), 0.0)
        qd = np.clip(qd, lo, hi)
        self.client.setJointMotorControlArray(
            self.robot,
            list(range(6)),
            self.client.VELOCITY_CONTROL,
            targetVelocities=qd.tolist(),
            forces=ur5.JOINT_TORQUE_NM.tolist(),
        )
        return qd

    def step(self) -> None:
        """Advance the simulation by one control period."""
        self.control_steps += 1
        target = int(round(self.control_steps * self.cfg.control_period_s * self.cfg.physics_hz))
        for _ in range(target - self.physics_steps):
            self.client.stepSimulation()
        self.physics_steps = target

    def clear_at(self, q: np.ndarray, margin_m: float = 0.02) -> bool:
        """Whether the arm at joints ``q`` keeps ``margin_m`` from the mesh, the table and the floor (its base
        and shoulder, mounted on the table, apart); the arm's state is put back exactly as it was."""
        c = self.client
        saved = c.getJointStates(self.robot, range(6))
        for j in range(6):
            c.resetJointState(self.robot, j, float(q[j]), 0.0)
        try:
            if c.getClosestPoints(self.robot, self.mesh_body, margin_m):
                return False
            return not any(
                p[3] > 0
                for body in (self.table, self.floor)
                for p in c.getClosestPoints(self.robot, body, margin_m)
            )
        finally:
            for j, st in enumerate(saved):
                c.resetJointState(self.robot, j, st[0], st[1])

    def measure_camera_after(self, q: np.ndarray) -> np.ndarray:
        """Where the camera would be at joints ``q``, measured on the simulated arm (no kinematic model).

        Used to calibrate PBVS's Jacobian numerically: the joints are set, the camera's pose read, and
        the arm's state put back exactly as it was.
        """
        saved = self.client.getJointStates(self.robot, range(6))
        for j in range(6):
            self.client.resetJointState(self.robot, j, float(q[j]), 0.0)
        T = self.world_from_camera()
        for j, s in enumerate(saved):
            self.client.resetJointState(self.robot, j, s[0], s[1])
        return T

    # --- kinematic model (set-up, IBVS, TCP approach; never PBVS) ------------------------------
    def base_from(self, link: str, q: np.ndarray) -> np.ndarray:
        F = {
            "flange": np.eye(4),
            "camera": self.layout.flange_from_camera,
            "tcp": self.layout.flange_from_tcp,
        }[link]
        return ur5.forward_kinematics(q) @ F

    def world_from_camera_model(self, q: np.ndarray) -> np.ndarray:
        return self.layout.world_from_base @ self.base_from("camera", q)

    # --- the mesh ------------------------------------------------------------------------------
    def surface_point(self, axial_m: float, arc_m: float) -> tuple[np.ndarray, np.ndarray]:
        """A point of the crossings' surface, ``axial_m`` along the axis and ``arc_m`` along the arc from
        the crown (planar meshes: along x and y from the centre; a mesh read from IFC: along the fitted
        surface's x and y from the bars' centre), and the outward normal there (world)."""
        lay = self.rm.layout
        if lay.surface is not None:
            p, _, _, n = MatSurface.of_crossings(lay, self.rm.crossings).frame(np.array([[axial_m, arc_m]]))
            return p[0], n[0]
        T = lay.world_from_mesh
        local_crossings = apply(rigid_inverse(T), self.rm.crossings.point)
        if lay.kind == "planar":
            p = np.array([axial_m, arc_m, float(np.median(local_crossings[:, 2]))])
            n = np.array([0.0, 0.0, 1.0])
        else:
            radial = local_crossings - lay.axis_point
            r = float(np.median(np.linalg.norm(radial[:, 1:], axis=1)))
            psi = arc_m / r
            n = np.array([0.0, np.sin(psi), np.cos(psi)])
            p = lay.axis_point + r * n + np.array([axial_m, 0.0, 0.0])
        return apply(T, p), T[:3, :3] @ n

    def camera_pose_for(self, start: StartPose) -> np.ndarray:
        """``world_from_camera`` of a start pose: the camera on the surface normal through the look-at point,
        image rows along the world's vertical where possible, then orbited (tilt) and rolled about that point."""
        p, n = self.surface_point(*start.look_at_m)
        z = -n
        down = np.array([0.0, 0.0, -1.0])
        y = down - (down @ z) * z
        if np.linalg.norm(y) < 1e-6:
            y = self.rm.layout.world_from_mesh[:3, 1] * -1.0
        y /= np.linalg.norm(y)
        x = np.cross(y, z)
        R0 = np.column_stack([x, y, z])
        tilt = Rotation.from_euler(
            "xyz", [start.tilt_deg[0], start.tilt_deg[1], start.roll_deg], degrees=True
        )
        R = R0 @ tilt.as_matrix()
        return make_transform(R, p - R[:, 2] * start.standoff_m)

    def solve_start(
        self, world_from_camera: np.ndarray, seed: np.ndarray | None = None
    ) -> tuple[np.ndarray, bool]:
        """Joint angles that put the camera at ``world_from_camera`` (IK from the home configuration, or from
        ``seed``), at least 0.3 rad inside every joint limit."""
        base_from_camera = rigid_inverse(self.layout.world_from_base) @ world_from_camera
        best: tuple[np.ndarray, bool] | None = None
        for q0 in [seed] if seed is not None else self.home_seeds():
            q, ok = ur5.inverse_kinematics(
                base_from_camera, q0, flange_from_point=self.layout.flange_from_camera, limits=self.limits
            )
            if ok and np.all(np.abs(q) < self.limits.upper - 0.3):
                return q, True
            best = best or (q, False)
        return best

    def home_seeds(self) -> list[np.ndarray]:
        if self.cfg.home_joints_rad is not None:
            return [np.array(self.cfg.home_joints_rad)]
        return [HOME_SEED]


# The arm looking at the crossings at (0, -0.05) from 0.6 m, elbow and wrist up (the arm stays clear of
# the table); start poses are solved from here so that every episode starts in this configuration.
HOME_SEED = np.array([-0.132, -1.954, -2.349, -1.964, -1.703, 3.144])


def check_reachable(world: ServoWorld, start: StartPose, where: str) -> np.ndarray:
    q, ok = world.solve_start(world.camera_pose_for(start))
    if not ok:
        raise ConfigError(
            f"{where}: the start pose looking at {start.look_at_m} from {start.standoff_m} m is out of the "
            "UR5's reach; accepted: a look_at_m nearer (0, 0) or a shorter standoff_m"
        )
    return q
