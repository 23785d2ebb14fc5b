"""Scenario programs: what the robot is told to do (TCP targets in the base frame [m]).

The camera stands in front of the robot (x ≈ 3.2 m in the base frame) looking back at
it; the LED hemisphere's axis (tool z) faces the camera when the tool is unrotated.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from .._errors import UserError
from ._motion import LINEAR_ACCELERATION, Corner, Move, ring, ring_peak

#: TCP orientation with tool z along base +x (toward the camera), tool y along base y
FACING_CAMERA = Rotation.from_matrix(np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]))

#: iso_cube: 30 pose cycles (the standard's number) and the path test
DEFAULT_DURATION = {
    "paper": 30.0,
    "calibration": 60.0,
    "workspace": 60.0,
    "iso_cube": 610.0,
    "crossing": 20.0,
}

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


def workspace(duration: float, rng: np.random.Generator) -> list[Move]:
    """As `calibration`, with the static poses spread over as much of the visible
    workspace as the robot reaches (the base turns by about ±0.8 rad, the arm from
    folded to stretched): the joint-space coverage a kinematic calibration wants, and
    that tells joint-angle functions (harmonics) apart."""
    n = max(6, int(duration / 2.6))
    shoulder = np.array([0.1, 0.0, 0.615])
    moves = []
    while len(moves) < n:
        p = rng.uniform([0.6, -0.9, 0.35], [1.45, 0.9, 1.6])
        if not 0.75 < np.linalg.norm(p - shoulder) < 1.3:
            continue
        axis = rng.normal(size=3)
        axis[0] = 0.0
        axis /= np.linalg.norm(axis)
        # face the camera (at x ≈ 3.2 m, y = 0) from where the tool is
        yaw = Rotation.from_euler("z", np.arctan2(-p[1], 3.2 - p[0]))
        tilt = Rotation.from_rotvec(np.deg2rad(rng.uniform(5.0, 30.0)) * axis)
        spin = Rotation.from_euler("x", rng.uniform(-90.0, 90.0), degrees=True)
        start = "start" if not moves else "joint"
        moves.append(Move(p, _q(yaw * tilt * spin * FACING_CAMERA), start, 0.0, 1.0))
    return moves


def iso_cube_poses() -> np.ndarray:
    """ISO 9283 test positions P1–P5 [m]: cube centre, then 80 % toward four corners of
    the diagonal plane y = z (relative to the centre)."""
    h = ISO_CUBE_SIDE / 2
    corners = np.array([[h, h, h], [-h, h, h], [-h, -h, -h], [h, -h, -h]])
    return ISO_CUBE_CENTRE + np.vstack([np.zeros(3), 0.8 * corners])


#: ISO 9283 truths injected by `iso_cube`, in the base frame (see `iso_cube_truth`):
#: attained − commanded position along the approach direction [m] (gives vAP)
ISO_CUBE_APPROACH_ERROR = 40e-6
#: attained − commanded position growing by this much per pose cycle [m] (gives dAP)
ISO_CUBE_DRIFT = np.array([3e-6, -1e-6, 2e-6])
#: ringing after each pose-test arrival along the approach: amplitude [m], τ [s], f [Hz]
ISO_CUBE_SETTLE = (2e-3, 0.06, 5.0)
ISO_CUBE_SPEED = 0.4  # [m/s] pose-test moves
ISO_CUBE_CYCLE_TIME = 13.5  # [s] one pose cycle (five moves, 1 s dwell each)
#: P1 → P5 → P4 → P3 → P2 → P1 in even cycles, the reverse in odd ones
ISO_CUBE_ORDER = ([4, 3, 2, 1, 0], [1, 2, 3, 4, 0])
#: path test corners at the positions of P3, P4, P5 (the rectangle's second to fourth
#: targets): corner zone [m] (gives CR) and amplitude [m] of the ringing across the next
#: leg (gives CO); the rectangle's start at P2 is a fine point (the robot stops there)
ISO_CUBE_CORNERS = ((2e-3, 2.5e-3), (3e-3, 3.5e-3), (4e-3, 3e-3))
#: decay time τ [s] and frequency [Hz] of the ringing after each corner
ISO_CUBE_CORNER_RING = (0.06, 5.0)


def iso_cube_cycles(duration: float) -> int:
    """Pose cycles of `iso_cube` in `duration` seconds (two thirds of it; at least 3)."""
    return max(3, int(duration * 2 / 3 / ISO_CUBE_CYCLE_TIME))


def iso_cube(duration: float, rng: np.random.Generator) -> list[Move]:
    """ISO 9283 cube test: `iso_cube_cycles(duration)` pose cycles through P1–P5 (1 s
    dwell), alternately in the two directions so each pose is approached from two sides,
    then a rectangular path through P2–P5 with reorientation, repeated.

    The pose-test moves carry the known truths of `iso_cube_truth`: an error along the
    approach direction, a drift growing with the cycle and a ringing after arrival. The
    path's corners at P3–P5 are flown by (`ISO_CUBE_CORNERS`, truths in
    `iso_cube_corner_truth`).
    """
    poses = iso_cube_poses()
    q0 = _q(FACING_CAMERA)
    speed = ISO_CUBE_SPEED
    n_cycles = iso_cube_cycles(duration)
    moves = [Move(poses[0], q0, "start", 0.0, 1.0)]
    for c in range(n_cycles):
        for k in ISO_CUBE_ORDER[c % 2]:
            prev = moves[-1].position
            u = (poses[k] - prev) / np.linalg.norm(poses[k] - prev)
            err = ISO_CUBE_APPROACH_ERROR * u + ISO_CUBE_DRIFT * c
            moves.append(Move(poses[k], q0, "linear", speed, 1.0, err, ISO_CUBE_SETTLE))
    rect = [poses[1], poses[2], poses[3], poses[4]]
    tilts = [_tilt("y", 15.0), _tilt("z", 15.0), _tilt("y", -15.0), _tilt("z", -15.0)]
    n_paths = max(2, int(duration / 3 / 9.0))
    moves.append(Move(rect[0], tilts[0], "linear", speed, 0.5))
    for _ in range(n_paths):
        for j, (zone, amp) in zip([1, 2, 3], ISO_CUBE_CORNERS):
            ringing = (amp, *ISO_CUBE_CORNER_RING)
            moves.append(
                Move(rect[j], tilts[j], "linear", 0.2, 0.0, zone=zone, corner_settle=ringing)
            )
        moves.append(Move(rect[0], tilts[0], "linear", 0.2, 0.5))
    moves.append(Move(poses[0], q0, "linear", speed, 0.5))
    return moves


def iso_cube_truth(
    duration: float, band: float, drift_cycles: int | None = None
) -> dict[str, dict[str, Any]]:
    """ISO 9283 characteristics `iso_cube` injects, per test pose ``P1``…``P5`` (named
    as the analysis names them: in order of first appearance in the program), with the
    `commanded` position [m].

    `AP_vector` `(3,)` [m]: mean attained − commanded position of the injected errors
    (what a robot free of every other error shows as AP; the approach errors of two
    directions that are not opposite do not cancel);
    `vAP` [m]: distance between the barycentres of the two approach directions
    (approach error × |u₁ − u₂|, plus the drift's share where the directions' cycles
    differ); `dAP` [m]: ||AP late| − |AP early|| over `drift_cycles` (default a third)
    cycles at each end; `overshoot` [m] and `t_stab` [s] of the ringing for limit band
    `band` [m] (time from entering the band on the decelerating approach until the
    ringing stays inside it).
    """
    n = iso_cube_cycles(duration)
    m = max(2, n // 3) if drift_cycles is None else drift_cycles
    poses = iso_cube_poses()
    errs: dict[int, list[tuple[int, np.ndarray, np.ndarray]]] = {}
    prev = poses[0]
    for c in range(n):
        for k in ISO_CUBE_ORDER[c % 2]:
            u = (poses[k] - prev) / np.linalg.norm(poses[k] - prev)
            errs.setdefault(k, []).append((c, u, ISO_CUBE_APPROACH_ERROR * u + ISO_CUBE_DRIFT * c))
            prev = poses[k]
    t = np.arange(0.0, 8.0 * ISO_CUBE_SETTLE[1], 1e-6)
    out_band = np.flatnonzero(np.abs(ring(t, ISO_CUBE_SETTLE)) > band)
    t_out = t[out_band[-1]] if out_band.size else 0.0
    t_enter = np.sqrt(2.0 * band / LINEAR_ACCELERATION)  # rest-to-rest deceleration
    # the analysis names poses in order of first appearance in the program
    out = {}
    for i, k in enumerate([0, *ISO_CUBE_ORDER[0][:-1]]):
        e = np.array([v[2] for v in errs[k]])
        dirs = np.array([v[1] for v in errs[k]])
        first = np.all(np.isclose(dirs, dirs[0]), axis=1)
        vap = float(np.linalg.norm(e[first].mean(0) - e[~first].mean(0)))
        dap = abs(float(np.linalg.norm(e[-m:].mean(0)) - np.linalg.norm(e[:m].mean(0))))
        out[f"P{i + 1}"] = {
            "commanded": poses[k],
            "vAP": vap,
            "dAP": dap,
            "overshoot": ring_peak(ISO_CUBE_SETTLE),
            "t_stab": float(t_out + t_enter),
            "AP_vector": e.mean(0),
        }
    return out


def iso_cube_corner_truth() -> dict[str, dict[str, Any]]:
    """Cornering characteristics `iso_cube` injects at the path test's corners, named as
    the analysis names them (the rectangle's start ``P6``, a test pose after P1–P5; the
    flown-by corners ``T1``–``T3``), with the `commanded` corner [m].

    `CR` [m]: distance from the corner to the arc that cuts it (zone·tan(φ/4) for a turn
    by φ); `CO` [m]: largest distance from the second leg after the corner: the larger of
    the ringing's first peak and the arc's own distance from that leg where it is nearer
    to it than to the first leg (CR·cos(φ/2), at the arc's middle). Zero at the fine
    point ``P6``. `zone` [m] and `ringing` (amplitude [m], τ [s], frequency [Hz]): what
    was injected (None at ``P6``).
    """
    rect = iso_cube_poses()[1:]
    out = {"P6": {"commanded": rect[0], "CR": 0.0, "CO": 0.0, "zone": None, "ringing": None}}
    for j, (zone, amp) in enumerate(ISO_CUBE_CORNERS, start=1):
        c = Corner.between(rect[j - 1], rect[j], rect[(j + 1) % 4], zone)
        ringing = (amp, *ISO_CUBE_CORNER_RING)
        co = max(ring_peak(ringing), c.round_off * np.cos(c.angle / 2))
        out[f"T{j}"] = {
            "commanded": rect[j],
            "CR": c.round_off,
            "CO": co,
            "zone": zone,
            "ringing": ringing,
        }
    return out


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


SCENARIOS = {
    "paper": paper,
    "calibration": calibration,
    "workspace": workspace,
    "iso_cube": iso_cube,
    "crossing": crossing,
}


def ideal_controller(moves: list[Move]) -> list[Move]:
    """`moves` as a controller without errors runs them: each target attained exactly, no
    drift, no ringing after arrival or corners (fly-by zones stay: they are the program's)."""
    return [dataclasses.replace(m, error=None, settle=None, corner_settle=None) for m in moves]


def scenario_moves(name: str, duration: float, rng: np.random.Generator) -> list[Move]:
    if name not in SCENARIOS:
        raise UserError(f"unknown scenario {name!r} (choose from {', '.join(SCENARIOS)})")
    return SCENARIOS[name](duration, rng)
