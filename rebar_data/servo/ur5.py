"""The UR5 arm from Universal Robots' published DH parameters: kinematics, Jacobian, limits and a URDF.

Standard (distal) DH convention, as Universal Robots publishes it: frame ``i`` is frame ``i-1`` times
``Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``, with ``theta_i`` the joint angle. The URDF written here
places joint ``i`` at DH frame ``i-1``, so the simulator's link frames and :func:`forward_kinematics`
agree exactly and joint angles are DH angles (the arm is stretched out horizontally at zero).

Frames: ``base`` is the robot's mounting frame (z up), ``flange`` is DH frame 6 (UR's ``tool0``: z out
of the flange).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

D_M = np.array([0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823])
A_M = np.array([0.0, -0.425, -0.39225, 0.0, 0.0, 0.0])
ALPHA_RAD = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
MASS_KG = np.array([3.7, 8.393, 2.275, 1.219, 1.219, 0.1879])
# Centres of mass in DH frame i (Universal Robots' dynamic parameters for the UR5).
COM_M = np.array(
    [
        [0.0, -0.02561, 0.00193],
        [0.2125, 0.0, 0.11336],
        [0.15, 0.0, 0.0265],
        [0.0, -0.0018, 0.01634],
        [0.0, 0.0018, 0.01634],
        [0.0, 0.0, -0.001159],
    ]
)
JOINT_LIMIT_RAD = 2 * np.pi
JOINT_SPEED_RAD_S = np.pi
JOINT_TORQUE_NM = np.array([150.0, 150.0, 150.0, 28.0, 28.0, 28.0])
REACH_M = 0.85
JOINT_NAMES = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")


@dataclass(frozen=True)
class JointLimits:
    """Position and speed limits of the six joints (radians, rad/s)."""

    lower: np.ndarray
    upper: np.ndarray
    speed: np.ndarray

    @staticmethod
    def ur5() -> JointLimits:
        return JointLimits(
            np.full(6, -JOINT_LIMIT_RAD), np.full(6, JOINT_LIMIT_RAD), np.full(6, JOINT_SPEED_RAD_S)
        )


def dh_transform(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    """``Rz(theta) Tz(d) Tx(a) Rx(alpha)`` as a 4x4 matrix."""
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def dh_frames(q: np.ndarray) -> np.ndarray:
    """``base_from_frame_i`` for i = 0..6, shape (7, 4, 4); frame 6 is the flange."""
    out = np.empty((7, 4, 4))
    out[0] = np.eye(4)
    for i in range(6):
        out[i + 1] = out[i] @ dh_transform(q[i], D_M[i], A_M[i], ALPHA_RAD[i])
    return out


def forward_kinematics(q: np.ndarray) -> np.ndarray:
    """``base_from_flange`` for joint angles ``q`` (radians)."""
    return dh_frames(np.asarray(q, float))[6]


def jacobian(q: np.ndarray, flange_from_point: np.ndarray | None = None) -> np.ndarray:
    """Geometric Jacobian (6x6) of a frame rigidly attached to the flange, in the base frame.

    Rows are (linear velocity of the frame's origin, angular velocity), columns the joint rates.
    """
    frames = dh_frames(np.asarray(q, float))
    T = frames[6] if flange_from_point is None else frames[6] @ flange_from_point
    p = T[:3, 3]
    J = np.empty((6, 6))
    for i in range(6):
        z, o = frames[i][:3, 2], frames[i][:3, 3]
        J[:3, i] = np.cross(z, p - o)
        J[3:, i] = z
    return J


def jacobian_in_frame(q: np.ndarray, flange_from_point: np.ndarray) -> np.ndarray:
    """The Jacobian of an attached frame expressed in that frame: joint rates to the frame's own twist."""
    T = forward_kinematics(q) @ flange_from_point
    R = T[:3, :3]
    J = jacobian(q, flange_from_point)
    return np.vstack([R.T @ J[:3], R.T @ J[3:]])


def inverse_kinematics(
    base_from_target: np.ndarray,
    q_start: np.ndarray,
    *,
    flange_from_point: np.ndarray | None = None,
    limits: JointLimits | None = None,
    iterations: int = 200,
    tolerance_m: float = 1e-6,
) -> tuple[np.ndarray, bool]:
    """Joint angles that put an attached frame at ``base_from_target`` (damped least squares from ``q_start``).

    Used to set up start poses, never inside a controller. Returns the angles and whether the pose was
    reached to ``tolerance_m`` (and 1e-5 rad).
    """
    limits = limits or JointLimits.ur5()
    F = np.eye(4) if flange_from_point is None else flange_from_point
    q = np.array(q_start, float)
    for _ in range(iterations):
        T = forward_kinematics(q) @ F
        dp = base_from_target[:3, 3] - T[:3, 3]
        dR = base_from_target[:3, :3] @ T[:3, :3].T
        dw = _rotation_vector(dR)
        if np.linalg.norm(dp) < tolerance_m and np.linalg.norm(dw) < 1e-5:
            return q, True
        J = jacobian(q, F)
        e = np.concatenate([dp, dw])
        mu2 = 1e-4
        dq = J.T @ np.linalg.solve(J @ J.T + mu2 * np.eye(6), e)
        step = np.max(np.abs(dq))
        if step > 0.3:
            dq *= 0.3 / step
        q = np.clip(q + dq, limits.lower, limits.upper)
    T = forward_kinematics(q) @ F
    ok = np.linalg.norm(base_from_target[:3, 3] - T[:3, 3]) < 10 * tolerance_m
    ok = ok and np.linalg.norm(_rotation_vector(base_from_target[:3, :3] @ T[:3, :3].T)) < 1e-4
    return q, bool(ok)


def _rotation_vector(R: np.ndarray) -> np.ndarray:
    """Axis times angle of a rotation matrix (robust near 0 and pi)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def _origin(xyz, rpy=(0.0, 0.0, 0.0)) -> str:
    x = " ".join(f"{v:.9g}" for v in xyz)
    r = " ".join(f"{v:.9g}" for v in rpy)
    return f'<origin xyz="{x}" rpy="{r}"/>'


def _cylinder_inertia(mass: float, radius: float, length: float) -> tuple[float, float, float]:
    ixx = mass * (3 * radius**2 + length**2) / 12.0
    return ixx, ixx, mass * radius**2 / 2.0


def _link(
    name: str,
    mass: float,
    com,
    shapes: list[tuple[tuple, tuple, float, float]],
    color: str,
    collision: bool = True,
) -> str:
    """A URDF link with a cylinder's inertia at ``com`` and cylinders ``(xyz, rpy, radius, length)``."""
    lines = [f'  <link name="{name}">']
    if mass > 0:
        r, length = (shapes[0][2], shapes[0][3]) if shapes else (0.02, 0.04)
        ixx, iyy, izz = _cylinder_inertia(mass, r, length)
        lines += [
            "    <inertial>",
            f"      {_origin(com)}",
            f'      <mass value="{mass:.6g}"/>',
            f'      <inertia ixx="{ixx:.6g}" iyy="{iyy:.6g}" izz="{izz:.6g}" ixy="0" ixz="0" iyz="0"/>',
            "    </inertial>",
        ]
    for xyz, rpy, radius, length in shapes:
        geom = f'<geometry><cylinder radius="{radius:.6g}" length="{length:.6g}"/></geometry>'
        lines.append(
            f"    <visual>{_origin(xyz, rpy)}{geom}"
            f'<material name="{name}_m"><color rgba="{color}"/></material></visual>'
        )
        if collision:
            lines.append(f"    <collision>{_origin(xyz, rpy)}{geom}</collision>")
    lines.append("  </link>")
    return "\n".join(lines)


def _rpy_of(R: np.ndarray) -> tuple[float, float, float]:
    """URDF roll-pitch-yaw (fixed-axis XYZ: R = Rz(yaw) Ry(pitch) Rx(roll))."""
    from scipy.spatial.transform import Rotation

    return tuple(Rotation.from_matrix(R).as_euler("xyz"))


def link_shapes() -> list[list[tuple[tuple, tuple, float, float]]]:
    """Cylinders ``(xyz, rpy, radius, length)`` per link 0..6 (base, six moving links), in URDF link frames.

    Link i's frame is the joint-i frame (DH frame i-1 turned by theta_i); the link body spans the
    offset ``Tz(d_i) Tx(a_i)`` to the next joint.
    """
    half = np.pi / 2
    return [
        [((0, 0, 0.03), (0, 0, 0), 0.075, 0.06)],
        [((0, 0, 0.045), (0, 0, 0), 0.06, 0.09)],
        [((-0.2125, 0, 0.136), (0, half, 0), 0.054, 0.425), ((0, 0, 0.07), (0, 0, 0), 0.06, 0.14)],
        [((-0.196, 0, 0.016), (0, half, 0), 0.04, 0.392), ((0, 0, 0.076), (0, 0, 0), 0.05, 0.14)],
        [((0, 0, 0.055), (0, 0, 0), 0.045, 0.11)],
        [((0, 0, 0.047), (0, 0, 0), 0.045, 0.095)],
        [((0, 0, 0.041), (0, 0, 0), 0.045, 0.082)],
    ]


def ur5_urdf(
    *,
    extra_links: dict[str, np.ndarray] | None = None,
    tool_length_m: float = 0.0,
    tool_mass_kg: float = 0.0,
    tool_collision: bool = True,
) -> str:
    """URDF text of the UR5 from the DH table, masses and limits above.

    ``extra_links`` adds frames fixed to the flange (name to ``flange_from_link``), such as the camera and
    the tool centre point; the flange itself is the link ``flange``. A tool of ``tool_length_m`` along
    the flange's z axis and ``tool_mass_kg`` is part of the flange link; ``tool_collision=False`` makes it
    visual only (the tying tool closes around bars the simulator would otherwise push it off).
    """
    shapes = link_shapes()
    colors = ["0.2 0.2 0.22 1", "0.55 0.7 0.85 1", "0.85 0.85 0.88 1", "0.85 0.85 0.88 1"]
    colors += ["0.55 0.7 0.85 1", "0.55 0.7 0.85 1", "0.3 0.3 0.32 1"]
    parts = ['<?xml version="1.0"?>', '<robot name="ur5">']
    parts.append(_link("base_link", 4.0, (0, 0, 0.03), shapes[0], colors[0]))
    for i in range(6):
        com_dh = np.append(COM_M[i], 1.0)
        to_next = dh_transform(0.0, D_M[i], A_M[i], ALPHA_RAD[i])
        com_link = (to_next @ com_dh)[:3]
        parts.append(_link(f"link_{i + 1}", MASS_KG[i], com_link, shapes[i + 1], colors[i + 1]))
    for i in range(6):
        parent = "base_link" if i == 0 else f"link_{i}"
        if i == 0:
            origin = _origin((0, 0, 0))
        else:
            origin = _origin((A_M[i - 1], 0.0, D_M[i - 1]), (ALPHA_RAD[i - 1], 0.0, 0.0))
        parts.append(
            f'  <joint name="{JOINT_NAMES[i]}" type="revolute">\n'
            f'    <parent link="{parent}"/><child link="link_{i + 1}"/>\n'
            f'    {origin}<axis xyz="0 0 1"/>\n'
            f'    <limit lower="{-JOINT_LIMIT_RAD:.9g}" upper="{JOINT_LIMIT_RAD:.9g}" '
            f'effort="{JOINT_TORQUE_NM[i]:g}" velocity="{JOINT_SPEED_RAD_S:.9g}"/>\n'
            '    <dynamics damping="0.0" friction="0.0"/>\n'
            "  </joint>"
        )
    tool = [((0, 0, tool_length_m / 2), (0, 0, 0), 0.025, tool_length_m)] if tool_length_m > 0 else []
    parts.append(
        _link(
            "flange",
            max(tool_mass_kg, 1e-3),
            (0, 0, tool_length_m / 2),
            tool,
            "0.9 0.5 0.1 1",
            tool_collision,
        )
    )
    parts.append(
        '  <joint name="flange_joint" type="fixed"><parent link="link_6"/><child link="flange"/>'
        f"{_origin((A_M[5], 0.0, D_M[5]), (ALPHA_RAD[5], 0.0, 0.0))}</joint>"
    )
    for name, T in (extra_links or {}).items():
        parts.append(_link(name, 0.02, (0, 0, 0), [], ""))
        parts.append(
            f'  <joint name="{name}_joint" type="fixed"><parent link="flange"/><child link="{name}"/>'
            f"{_origin(T[:3, 3], _rpy_of(T[:3, :3]))}</joint>"
        )
    parts.append("</robot>")
    return "\n".join(parts) + "\n"
