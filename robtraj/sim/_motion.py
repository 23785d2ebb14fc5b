"""Robot motion from a program: trapezoidal speed profiles, linear and joint moves, IK.

All times here are on the robot clock [s]; poses in the base frame [m].
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .._errors import UserError
from ..model import RobotModel, forward_kinematics, inverse_kinematics

LINEAR_ACCELERATION = 1.5  # [m/s²]
ANGULAR_SPEED = 0.6  # [rad/s] TCP reorientation speed limit of linear moves
ANGULAR_ACCELERATION = 2.0  # [rad/s²]
JOINT_SPEED = 0.8  # [rad/s] of the fastest joint in joint moves
JOINT_ACCELERATION = 3.0  # [rad/s²]


@dataclasses.dataclass(frozen=True)
class Move:
    """One program step: reach `position`/`quaternion_wxyz` (TCP in base) then dwell.

    `error` [m]: the robot attains `position + error` instead (the program keeps
    `position`). `settle` = (amplitude [m], decay time τ [s], frequency [Hz]): after a
    linear move the TCP rings about the attained position along the move's direction,
    amplitude·e^(−t/τ)·sin(2π·frequency·t), t from the arrival.

    `zone` [m] makes this target a fly-by corner between two linear moves (no dwell):
    the TCP leaves the straight line `zone` before the target and joins the next move
    `zone` after it on a circular arc tangent to both (`Corner.arc`), so it never reaches
    the target. The timing stays rest-to-rest: the TCP comes to rest at the arc's middle.
    `corner_settle` = (amplitude [m], τ [s], frequency [Hz]): from where the TCP joins
    the next move it rings across it, toward the outside of the corner, as `settle` does
    (for at most 8τ, within that move).
    """

    position: np.ndarray
    quaternion_wxyz: np.ndarray
    motion: str  # "start", "linear" or "joint"
    speed: float  # [m/s]
    dwell: float  # [s] standing still after arriving
    error: np.ndarray | None = None
    settle: tuple[float, float, float] | None = None
    zone: float = 0.0
    corner_settle: tuple[float, float, float] | None = None

    @property
    def attained(self) -> np.ndarray:
        return self.position if self.error is None else self.position + self.error


def trapezoid_duration(distance: float, speed: float, acceleration: float) -> float:
    """Time [s] to cover `distance` from rest to rest with a trapezoidal speed profile."""
    if distance <= 0:
        return 0.0
    if distance < speed**2 / acceleration:
        return 2.0 * np.sqrt(distance / acceleration)
    return distance / speed + speed / acceleration


def trapezoid_progress(t: np.ndarray, duration: float, accel_time: float) -> np.ndarray:
    """Normalised progress s(t) ∈ [0, 1] of a rest-to-rest trapezoidal profile."""
    ta = min(accel_time, duration / 2)
    vmax = 1.0 / (duration - ta)
    t = np.clip(t, 0.0, duration)
    return np.where(
        t < ta,
        0.5 * vmax / ta * t**2,
        np.where(
            t <= duration - ta,
            0.5 * vmax * ta + vmax * (t - ta),
            1.0 - 0.5 * vmax / ta * (duration - t) ** 2,
        ),
    )


def trapezoid_time(s: np.ndarray | float, duration: float, accel_time: float) -> np.ndarray:
    """Time [s] at which `trapezoid_progress` reaches `s` ∈ [0, 1] (its inverse)."""
    ta = min(accel_time, duration / 2)
    vmax = 1.0 / (duration - ta)
    s = np.clip(s, 0.0, 1.0)
    s_a = 0.5 * vmax * ta  # progress at the end of the acceleration
    return np.where(
        s < s_a,
        np.sqrt(2.0 * s * ta / vmax),
        np.where(
            s <= 1.0 - s_a,
            ta + (s - s_a) / vmax,
            duration - np.sqrt(2.0 * np.clip(1.0 - s, 0.0, None) * ta / vmax),
        ),
    )


@dataclasses.dataclass(frozen=True)
class Corner:
    """A fly-by corner at `point` [m] between the move along unit `d1` and the next one,
    turning by `angle` [rad], cut by an arc tangent to both legs `zone` [m] from the
    corner: radius `zone`·cot(angle/2). `turn`: unit vector ⊥ `d1` toward the next leg;
    `outward`: unit vector ⊥ the next leg away from the inside of the corner."""

    point: np.ndarray
    d1: np.ndarray
    angle: float
    zone: float
    turn: np.ndarray
    outward: np.ndarray

    @classmethod
    def between(cls, before: np.ndarray, point: np.ndarray, after: np.ndarray, zone: float):
        d1 = (point - before) / np.linalg.norm(point - before)
        d2 = (after - point) / np.linalg.norm(after - point)
        cos = float(np.clip(d1 @ d2, -1.0, 1.0))
        turn, outward = d2 - cos * d1, d1 - cos * d2
        return cls(point, d1, float(np.arccos(cos)), zone,
                   turn / np.linalg.norm(turn), outward / np.linalg.norm(outward))  # fmt: skip

    @property
    def round_off(self) -> float:
        """Distance [m] from the corner to the arc (its middle): zone·tan(angle/4)."""
        return self.zone * float(np.tan(self.angle / 4))

    def arc(self, beta: np.ndarray) -> np.ndarray:
        """`(n, 3)` points [m] of the arc after turning by `beta` ∈ [0, angle] [rad] from
        where it leaves the first leg."""
        r = self.zone / np.tan(self.angle / 2)
        return (self.point - self.zone * self.d1 + r * np.sin(beta)[:, None] * self.d1
                + r * (1.0 - np.cos(beta))[:, None] * self.turn)  # fmt: skip


def ring(t: np.ndarray, settle: tuple[float, float, float]) -> np.ndarray:
    """Ringing amplitude·e^(−t/τ)·sin(2π·frequency·t) [m] at times `t` [s] from its start."""
    amp, tau, freq = settle
    return amp * np.exp(-t / tau) * np.sin(2.0 * np.pi * freq * t)


def ring_peak(settle: tuple[float, float, float]) -> float:
    """Largest excursion [m] of `ring`: at t = atan(ωτ)/ω (ω = 2π·frequency)."""
    _, tau, freq = settle
    w = 2.0 * np.pi * freq
    return float(ring(np.array([np.arctan(w * tau) / w]), settle)[0])


def _corners(moves: list[Move]) -> list[Corner | None]:
    """The fly-by corner at each target (None where the robot passes through it)."""
    out: list[Corner | None] = [None] * len(moves)
    for i, m in enumerate(moves):  # program targets, not frames
        if m.zone <= 0:
            continue
        fly_by = 0 < i < len(moves) - 1 and m.dwell == 0 and m.motion == "linear"
        if not (fly_by and moves[i + 1].motion == "linear"):
            raise UserError("a corner zone needs linear moves on both sides and no dwell")
        c = Corner.between(moves[i - 1].attained, m.attained, moves[i + 1].attained, m.zone)
        if not 1e-6 < c.angle < np.pi - 1e-6:
            raise UserError("a corner zone needs moves that change direction and do not reverse")
        out[i] = c
    for i in range(1, len(moves)):
        ends = [c.zone for c in (out[i - 1], out[i]) if c is not None]
        if sum(ends) > np.linalg.norm(moves[i].attained - moves[i - 1].attained):
            raise UserError("corner zones overlap on a move shorter than their sum")
    return out


def _rest_to_rest(distance: float, speed: float, acceleration: float) -> tuple[float, float]:
    d = trapezoid_duration(distance, speed, acceleration)
    return d, min(speed / acceleration, d / 2)


@jax.jit
def _ik_track(robot, poses, q_direct, use_direct, q0):
    def step(q_prev, x):
        pose, qd, direct = x
        q = jax.lax.cond(
            direct,
            lambda: qd,
            lambda: inverse_kinematics(robot, jaxlie.SE3(pose), q_prev, iterations=4),
        )
        return q, q

    return jax.lax.scan(step, q0, (poses, q_direct, use_direct))[1]


@jax.jit
def _fk_batch(robot, q):
    return jax.vmap(lambda qq: forward_kinematics(robot, qq).wxyz_xyz)(q)


def _fk_in_chunks(robot, q: np.ndarray, chunk: int = 2**16) -> np.ndarray:
    """`_fk_batch` of `q` `(K, J)` as `(K, 7)`, `chunk` configurations at a time (its
    intermediates take about a kilobyte per configuration; one compilation: the last
    chunk is padded)."""
    size = min(chunk, q.shape[0])
    out = np.empty((q.shape[0], 7))
    for start in range(0, q.shape[0], size):
        part = q[start : start + size]
        padded = np.pad(part, [(0, size - part.shape[0]), (0, 0)], mode="edge")
        got = np.asarray(_fk_batch(robot, jnp.asarray(padded)))
        out[start : start + part.shape[0]] = got[: part.shape[0]]
    return out


@jax.jit
def _ik_solve(robot, base_from_flange, seed):
    q = inverse_kinematics(robot, base_from_flange, seed, iterations=80)
    return q, (base_from_flange.inverse() @ forward_kinematics(robot, q)).log()


def _ik_point(robot, base_from_flange: jaxlie.SE3, seed: np.ndarray) -> np.ndarray:
    q, err = _ik_solve(robot, base_from_flange, jnp.asarray(seed))
    if not np.all(np.isfinite(q)) or float(jnp.max(jnp.abs(err))) > 1e-9:
        p = np.round(np.asarray(base_from_flange.translation()), 3)
        raise UserError(f"program target at {p.tolist()} m is out of the robot's reach")
    return np.asarray(q)


def joint_log(
    robot: RobotModel,
    moves: list[Move],
    flange_from_tool: jaxlie.SE3,
    q_seed: np.ndarray,
    times: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint angles the controller commands at robot-clock `times` for a program.

    Returns ``(joints (K, J), departure (P,), arrival (P,))``: robot times at which the
    move to each target starts and ends (the first target: −inf and 0; the robot holds
    the first pose before time 0 and the last pose after the end). The program segment
    of a time t is the last target whose move has started.
    """
    tool_from_flange = flange_from_tool.inverse()
    tff_rot = Rotation.from_quat(np.asarray(tool_from_flange.rotation().wxyz), scalar_first=True)
    tff_pos = np.array(tool_from_flange.translation())

    def flange_target(m: Move) -> jaxlie.SE3:
        tcp = jaxlie.SE3.from_rotation_and_translation(
            jaxlie.SO3(jnp.asarray(m.quaternion_wxyz)), jnp.asarray(m.attained)
        )
        return tcp @ tool_from_flange

    corners = _corners(moves)
    q_targets = [_ik_point(robot, flange_target(moves[0]), q_seed)]
    starts, durations, accel = [], [], []
    t = moves[0].dwell
    arrival = [0.0]
    for i in range(1, len(moves)):
        a, b = moves[i - 1], moves[i]
        q_targets.append(_ik_point(robot, flange_target(b), q_targets[-1]))
        if b.motion == "joint":
            dq = float(np.max(np.abs(q_targets[-1] - q_targets[-2])))
            d, ta = _rest_to_rest(dq, JOINT_SPEED, JOINT_ACCELERATION)
        else:
            dist = float(np.linalg.norm(b.attained - a.attained))
            ang = (
                Rotation.from_quat(a.quaternion_wxyz, scalar_first=True).inv()
                * Rotation.from_quat(b.quaternion_wxyz, scalar_first=True)
            ).magnitude()
            d1, ta1 = _rest_to_rest(dist, b.speed, LINEAR_ACCELERATION)
            d2, ta2 = _rest_to_rest(float(ang), ANGULAR_SPEED, ANGULAR_ACCELERATION)
            d, ta = (d1, ta1) if d1 >= d2 else (d2, ta2)
        d = max(d, 1e-3)
        starts.append(t)
        durations.append(d)
        accel.append(ta)
        t += d
        arrival.append(t)
        t += b.dwell

    k = len(times)
    n_j = robot.n_joints
    poses = np.zeros((k, 7))
    poses[:, 0] = 1.0
    q_direct = np.zeros((k, n_j))
    use_direct = np.ones(k, bool)
    q_direct[:] = q_targets[0]
    for i in range(1, len(moves)):
        s0, d = starts[i - 1], durations[i - 1]
        moving = (times > s0) & (times <= s0 + d)
        q_direct[times > s0 + d] = q_targets[i]
        s = trapezoid_progress(times[moving] - s0, d, accel[i - 1])
        a, b = moves[i - 1], moves[i]
        if b.motion == "joint":
            q_direct[moving] = q_targets[i - 1] + s[:, None] * (q_targets[i] - q_targets[i - 1])
            continue
        step = b.attained - a.attained
        pos = a.attained + s[:, None] * step
        length = float(np.linalg.norm(step))
        start, end = corners[i - 1], corners[i]
        if start is not None:  # leave the previous corner's arc, then ring across this move
            u = s * length
            on = u < start.zone
            pos[on] = start.arc(0.5 * start.angle * (1.0 + u[on] / start.zone))
            if moves[i - 1].corner_settle is not None:
                settle = moves[i - 1].corner_settle
                joined = s0 + float(trapezoid_time(start.zone / length, d, accel[i - 1]))
                dt = times[moving] - joined
                r = (dt > 0) & (dt <= 8.0 * settle[1])
                pos[r] += ring(dt[r], settle)[:, None] * start.outward
        if end is not None:  # onto this target's arc
            u = (1.0 - s) * length
            on = u < end.zone
            pos[on] = end.arc(0.5 * end.angle * (1.0 - u[on] / end.zone))
        ends = np.stack([a.quaternion_wxyz, b.quaternion_wxyz])
        rots = Slerp([0.0, 1.0], Rotation.from_quat(ends, scalar_first=True))(s)
        flange_rot = rots * tff_rot
        poses[moving, :4] = flange_rot.as_quat(scalar_first=True)
        poses[moving, 4:] = pos + rots.apply(tff_pos)
        use_direct[moving] = False
        if b.settle is not None and length > 0:
            dt = times - (s0 + d)
            rings = (dt > 0) & (dt <= min(b.dwell, 8.0 * b.settle[1]))
            rot = Rotation.from_quat(b.quaternion_wxyz, scalar_first=True)
            tcp = b.attained + ring(dt[rings], b.settle)[:, None] * step / length
            poses[rings, :4] = (rot * tff_rot).as_quat(scalar_first=True)
            poses[rings, 4:] = tcp + rot.apply(tff_pos)
            use_direct[rings] = False
    q = np.asarray(
        _ik_track(
            robot,
            jnp.asarray(poses),
            jnp.asarray(q_direct),
            jnp.asarray(use_direct),
            jnp.asarray(q_targets[0]),
        )
    )
    check = ~use_direct
    if np.any(check):
        got = _fk_in_chunks(robot, q[check])
        pos_err = np.max(np.abs(got[:, 4:] - poses[check][:, 4:]))
        jump = np.max(np.abs(np.diff(q, axis=0)))
        if not np.isfinite(pos_err) or pos_err > 1e-7 or jump > 0.1:
            raise UserError("a linear move leaves the robot's reach or passes a singularity")
    return q, np.array([-np.inf, *starts]), np.asarray(arrival)
