"""A robot model as URDF text: the DH chain written as URDF joints, for the cell's tools.

Link ``link_i`` is DH frame i−1 turned by joint i; joint i's origin is the previous DH
row's transform ``Rz(θ₀)·Tz(d)·Tx(a)·Rx(α)`` (joint 1 at the base), its axis z; the
fixed joint ``flange`` carries the last row and `last_from_flange` to link ``tool0``.
Each link's mass sits where the lumped-mass model puts it (the middle of its DH link);
the payload is the mass of ``tool0``. A joint with limits is ``revolute`` with them as
``<limit lower upper>`` (an open side as ``inf``), one without (or a robot whose limits
are not known) ``continuous``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ._kinematics import RobotModel


def dh_link_matrix(row, tilt: float = 0.0) -> np.ndarray:
    """`(4, 4)` homogeneous transform ``Rz(θ₀)·Tz(d)·Tx(a)·Rx(α)·Ry(β)`` of one DH row
    ``[d, a, alpha, theta_offset]`` [m, m, rad, rad] with Hayati's `tilt` β [rad] (NumPy,
    joint angle 0; as `joint_frames`)."""
    d, a, alpha, theta0 = row
    ct, st, ca, sa = np.cos(theta0), np.sin(theta0), np.cos(alpha), np.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    ) @ _ry(tilt)


def _ry(beta: float) -> np.ndarray:
    c, s = np.cos(beta), np.sin(beta)
    return np.array([[c, 0.0, s, 0.0], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, c, 0.0], [0, 0, 0, 1.0]])


def _origin(t: np.ndarray) -> str:
    rpy = Rotation.from_matrix(t[:3, :3]).as_euler("xyz")
    xyz = " ".join(repr(float(v)) for v in t[:3, 3])
    return f'<origin xyz="{xyz}" rpy="{" ".join(repr(float(v)) for v in rpy)}"/>'


def _inertial(mass: float, centre: np.ndarray) -> str:
    xyz = " ".join(repr(float(v)) for v in centre)
    return (
        f'<inertial><origin xyz="{xyz}" rpy="0 0 0"/><mass value="{float(mass)!r}"/>'
        '<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>'
    )


def _joint_type_and_limit(limits: np.ndarray | None, i: int) -> tuple[str, str]:
    """URDF joint type and ``<limit>`` element of joint `i` for `limits` `(J, 2)` [rad]."""
    if limits is None or not np.isfinite(limits[i]).any():
        return "continuous", '<limit effort="1000" velocity="3"/>'
    lower, upper = (repr(float(v)) for v in limits[i])
    return "revolute", f'<limit lower="{lower}" upper="{upper}" effort="1000" velocity="3"/>'


def urdf_text(
    robot: RobotModel,
    name: str | None = None,
    *,
    tilt: np.ndarray | None = None,
    flange_from_tool: np.ndarray | None = None,
    notes: tuple[str, ...] = (),
) -> str:
    """URDF of `robot` (base link ``base_link``, flange link ``tool0``), metres and
    radians; its forward kinematics is `forward_kinematics(robot, q, tilt=tilt)`.

    `tilt` `(joints,)` [rad]: Hayati's turn of each link frame about its y axis (in the
    joint origins' rpy); `flange_from_tool` `(4, 4)`: a link ``tool`` fixed to ``tool0``
    there (the TCP); `notes`: lines written as XML comments (e.g. what the URDF cannot
    carry)."""
    dh = np.asarray(robot.dh, np.float64)
    beta = np.zeros(dh.shape[0]) if tilt is None else np.asarray(tilt, np.float64)
    masses = np.asarray(robot.link_mass, np.float64)
    limits = None if robot.joint_limits is None else np.asarray(robot.joint_limits, np.float64)
    flange = np.asarray(robot.last_from_flange, np.float64)  # wxyz_xyz
    last_from_flange = np.eye(4)
    last_from_flange[:3, :3] = Rotation.from_quat(flange[[1, 2, 3, 0]]).as_matrix()
    last_from_flange[:3, 3] = flange[4:]
    lines = ['<?xml version="1.0"?>', f'<robot name="{name or robot.name}">']
    lines += [f"  <!-- {note.replace('--', '- -')} -->" for note in notes]
    lines.append('  <link name="base_link"/>')
    parent = "base_link"
    for i in range(dh.shape[0]):
        link = f"link_{i + 1}"
        centre = 0.5 * dh_link_matrix(dh[i])[:3, 3]
        lines.append(f'  <link name="{link}">{_inertial(masses[i], centre)}</link>')
        origin = np.eye(4) if i == 0 else dh_link_matrix(dh[i - 1], beta[i - 1])
        kind, limit = _joint_type_and_limit(limits, i)
        lines.append(
            f'  <joint name="joint_{i + 1}" type="{kind}"><parent link="{parent}"/>'
            f'<child link="{link}"/>{_origin(origin)}<axis xyz="0 0 1"/>{limit}</joint>'
        )
        parent = link
    tool0 = dh_link_matrix(dh[-1], beta[-1]) @ last_from_flange
    payload = _inertial(float(robot.payload_mass), np.zeros(3))
    lines.append(f'  <link name="tool0">{payload}</link>')
    lines.append(
        f'  <joint name="flange" type="fixed"><parent link="{parent}"/><child link="tool0"/>'
        f"{_origin(tool0)}</joint>"
    )
    if flange_from_tool is not None:
        lines.append('  <link name="tool"/>')
        lines.append(
            '  <joint name="tcp" type="fixed"><parent link="tool0"/><child link="tool"/>'
            f"{_origin(np.asarray(flange_from_tool, np.float64))}</joint>"
        )
    lines.append("</robot>")
    return "\n".join(lines) + "\n"
