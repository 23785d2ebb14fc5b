"""Scenario programs: what the robot is told to do (TCP targets in the base frame [m]).

The camera stands in front of the robot (x ≈ 3.2 m in the base frame) looking back at
it; the LED hemisphere's axis (tool z) faces the camera when the tool is unrotated.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .._errors import UserError
from ._motion import Move

#: TCP orientation with tool z along base +x (toward the camera), tool y along base y
FACING_CAMERA = Rotation.from_matrix(np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]))

DEFAULT_DURATION = {"paper": 30.0, "calibration": 60.0, "iso_cube": 60.0, "crossing": 20.0}

#: ISO 9283 cube used by `iso_cube`: centre in the base frame [m] and side [m]
ISO_CUBE_CENTRE = np.array([1.15, 0.0, 0.95])
ISO_CUBE_SIDE = 0.4


def _q(rot: Rotation) -> np.ndarray:
    return rot.as_quat(scalar_first=True)


def _tilt(axis: str, deg: float) -> np.ndarray:
    return _q(Rotation.from_euler(axis, deg, degrees=True) * FACING_CAMERA)


def paper(duration: float, rng: np.random.Generator) -> list[Move]:
    """The paper's Figures 3–4: linear segment, stationary reorientation, perpendicular line.

    Speeds scale so the program fills about `duration` seconds.
    """
    k = 30.0 / duration
    v = 0.05 * k
    p0 = np.array([1.05, -0.25, 1.0])
    p1 = np.array([1.05, 0.25, 1.0])
    p2 = np.array([1.05, 0.25, 1.35])
    return [
        Move(p0, _tilt("z", -20.0), "start", 0.0, 1.3),
        Move(p1, _tilt("z", -20.0), "linear", v, 1.3),
        Move(p1, _tilt("y", 45.0), "linear", v, 0.5),
        Move(p1, _tilt("y", -45.0), "linear", v, 0.5),
        Move(p1, _tilt("z", 35.0), "linear", v, 1.3),
        Move(p2, _tilt("z", 35.0), "linear", v, 1.3),
    ]


def calibration(duration: float, rng: np.random.Generator) -> list[Move]:
    """Static poses spread over the workspace, joint moves between, 1 s dwell each."""
    n = max(6, int(duration / 2.6))
    moves = []
    for i in range(n):
        p = rng.uniform([0.9, -0.35, 0.75], [1.3, 0.35, 1.3])
        axis = rng.normal(size=3)
        axis[0] = 0.0  # tilt about axes across the line of sight
        axis /= np.linalg.norm(axis)
        tilt = Rotation.from_rotvec(np.deg2rad(rng.uniform(5.0, 35.0)) * axis)
        spin = Rotation.from_euler("x", rng.uniform(-90.0, 90.0), degrees=True)
        moves.append(
            Move(p, _q(tilt * spin * FACING_CAMERA), "start" if i == 0 else "joint", 0.0, 1.0)
        )
    return moves


def iso_cube_poses() -> np.ndarray:
    """ISO 9283 test positions P1–P5 [m]: cube centre, then 80 % toward four corners of
    the diagonal plane y = z (relative to the centre)."""
    h = ISO_CUBE_SIDE / 2
    corners = np.array([[h, h, h], [-h, h, h], [-h, -h, -h], [h, -h, -h]])
    return ISO_CUBE_CENTRE + np.vstack([np.zeros(3), 0.8 * corners])


def iso_cube(duration: float, rng: np.random.Generator) -> list[Move]:
    """ISO 9283 cube test: pose cycles P1→P5→P4→P3→P2 (1 s dwell), then a rectangular
    path through P2–P5 with reorientation, repeated.

    The number of pose cycles fills two thirds of `duration`; the path test the rest.
    """
    poses = iso_cube_poses()
    q0 = _q(FACING_CAMERA)
    speed = 0.4
    cycle = [0, 4, 3, 2, 1]
    n_cycles = max(3, int(duration * 2 / 3 / 9.0))
    moves = [Move(poses[0], q0, "start", 0.0, 1.0)]
    for _ in range(n_cycles):
        for k in cycle[1:] + cycle[:1]:
            moves.append(Move(poses[k], q0, "linear", speed, 1.0))
    rect = [poses[1], poses[2], poses[3], poses[4]]
    tilts = [_tilt("y", 15.0), _tilt("z", 15.0), _tilt("y", -15.0), _tilt("z", -15.0)]
    n_paths = max(2, int(duration / 3 / 9.0))
    moves.append(Move(rect[0], tilts[0], "linear", speed, 0.5))
    for _ in range(n_paths):
        for j in [1, 2, 3, 0]:
            moves.append(Move(rect[j], tilts[j], "linear", 0.2, 0.0))
        moves[-1] = Move(rect[0], tilts[0], "linear", 0.2, 0.5)
    moves.append(Move(poses[0], q0, "linear", speed, 0.5))
    return moves


def crossing(duration: float, rng: np.random.Generator) -> list[Move]:
    """A bow-tie that crosses itself, then parallel passes 5 mm apart."""
    q0 = _q(FACING_CAMERA)
    c = np.array([1.1, 0.0, 1.0])
    v = 0.1 * 20.0 / duration
    pts = [(-0.15, -0.1), (0.15, 0.1), (0.15, -0.1), (-0.15, 0.1), (-0.15, -0.1)]
    moves = [Move(c + [0, *pts[0]], q0, "start", 0.0, 0.5)]
    moves += [Move(c + [0, y, z], q0, "linear", v, 0.0) for y, z in pts[1:]]
    moves += [
        Move(c + [0, 0.15, -0.1], q0, "linear", v, 0.0),
        Move(c + [0, 0.15, -0.095], q0, "linear", v, 0.0),
        Move(c + [0, -0.15, -0.095], q0, "linear", v, 0.5),
    ]
    return moves


SCENARIOS = {"paper": paper, "calibration": calibration, "iso_cube": iso_cube, "crossing": crossing}


def scenario_moves(name: str, duration: float, rng: np.random.Generator) -> list[Move]:
    if name not in SCENARIOS:
        raise UserError(f"unknown scenario {name!r} (choose from {', '.join(SCENARIOS)})")
    return SCENARIOS[name](duration, rng)
