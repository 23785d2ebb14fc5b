"""Synthetic programs and measured trajectories with known injected errors (no simulator)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from robtraj.analysis._quat import quat_multiply, slerp
from robtraj.recording import Pose, Program

CENTRE = np.array([1.15, 0.0, 0.95])


def quat(rotvec) -> np.ndarray:
    return Rotation.from_rotvec(np.atleast_2d(rotvec)).as_quat()[:, [3, 0, 1, 2]]


def cube_program(
    cycles: int, path_cycles: int, alternate: bool = False
) -> tuple[Program, np.ndarray]:
    """ISO cube test: P1 centre, P2–P5 at 0.8 of the way to corners of a diagonal plane,
    cycles P1→P5→P4→P3→P2 (every other cycle reversed with `alternate`: each pose
    approached from two directions), then a rectangle with reorientation `path_cycles`
    times. Returns the program and a `(P,)` bool "dwell here" flag."""
    h = 0.2 * 0.8
    corners = np.array([[-1, -1, -1], [-1, 1, -1], [1, 1, 1], [1, -1, 1]]) * h
    poses = np.concatenate([[CENTRE], CENTRE + corners])  # P1..P5
    pq = quat(np.array([[0.0, 0.0, 0.0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1], [0.05, 0.05, 0]]))
    pq = quat_multiply(pq, quat([np.pi, 0, 0])[0])  # tool pointing down
    order = [0, 4, 3, 2, 1]
    pos, q, motion, dwell = [poses[0]], [pq[0]], ["start"], [True]
    for c in range(cycles):
        for i in (order[:0:-1] if alternate and c % 2 else order[1:]) + [0]:
            pos.append(poses[i]), q.append(pq[i]), motion.append("joint"), dwell.append(True)
    rect = CENTRE + np.array([[-0.15, -0.1, 0], [0.15, -0.1, 0], [0.15, 0.1, 0], [-0.15, 0.1, 0]])
    rq = quat(np.array([[0, 0, 0], [0, 0, 0.5], [0, 0.2, 0.5], [0, 0.2, 0]]))
    rq = quat_multiply(rq, quat([np.pi, 0, 0])[0])
    pos.append(rect[0]), q.append(rq[0]), motion.append("joint"), dwell.append(False)
    for _ in range(path_cycles):
        for i in [1, 2, 3, 0]:
            pos.append(rect[i]), q.append(rq[i]), motion.append("linear"), dwell.append(False)
    prog = Program(Pose(np.array(pos), np.array(q)), np.array(motion), np.full(len(pos), 0.2))
    return prog, np.array(dwell)


def attained(prog: Program, offset, sigma, rot_offset, rot_sigma, rng):
    """Per-target attained poses: command + constant offset + N(0, sigma) per axis, and
    orientation error rotation exp(rot_offset + N(0, rot_sigma)) applied in the base frame."""
    p = prog.targets.position
    n = p.shape[0]
    pos = p + offset + rng.normal(0.0, sigma, (n, 3))
    rv = rot_offset + rng.normal(0.0, rot_sigma, (n, 3))
    q = quat_multiply(quat(rv), prog.targets.quaternion_wxyz)
    return pos, q


def trajectory(
    prog: Program,
    pos,
    q,
    dwell,
    rate=100.0,
    dwell_time=1.0,
    noise=0.0,
    rng=None,
    speed_scale=1.0,
    ripple=None,
):
    """Straight moves between the attained poses with dwells; returns time, position,
    quaternion, segment (target approached; during a dwell, that target).

    Speed `speed_scale` × commanded (a scalar or one per target); `ripple` = (a, f): the
    speed of linear moves is v·(1 + a·cos 2πf't), f' the nearest frequency that fits an
    even number of periods into the move (at least two): the middle half of the move
    then holds whole periods.
    """
    ts, ps, qs, segs = [], [], [], []
    t0 = 0.0
    dt = 1.0 / rate
    scale = np.broadcast_to(np.asarray(speed_scale, np.float64), (pos.shape[0],))
    for j in range(1, pos.shape[0]):
        length = np.linalg.norm(pos[j] - pos[j - 1])
        dur = max(length / (scale[j] * prog.speed[j]), 0.2)
        k = max(int(np.ceil(dur / dt)), 1)
        u = np.arange(k) / k  # time fraction
        s = u  # progress
        if ripple is not None and prog.motion[j] == "linear":
            w = 4 * np.pi * max(round(ripple[1] * dur / 2), 1) / dur
            s = u + ripple[0] / (w * dur) * np.sin(w * u * dur)
        ts.append(t0 + u * dur)
        ps.append(pos[j - 1] + s[:, None] * (pos[j] - pos[j - 1]))
        qs.append((np.broadcast_to(q[j - 1], (k, 4)), np.broadcast_to(q[j], (k, 4)), s))
        segs.append(np.full(k, j))
        t0 += dur
        if dwell[j]:
            m = int(dwell_time * rate)
            ts.append(t0 + np.arange(m) * dt)
            ps.append(np.broadcast_to(pos[j], (m, 3)))
            qs.append((np.broadcast_to(q[j], (m, 4)), np.broadcast_to(q[j], (m, 4)), np.zeros(m)))
            segs.append(np.full(m, j))
            t0 += m * dt
    t = np.concatenate(ts)
    p = np.concatenate(ps)
    if noise:
        p = p + rng.normal(0.0, noise, p.shape)
    q0, q1, frac = (np.concatenate(v) for v in zip(*qs))
    return t, p, slerp(q0, q1, frac), np.concatenate(segs)  # one call: one compiled shape


def round_corners(prog: Program, t, p, seg, radius: float) -> np.ndarray:
    """`p` with each corner between two consecutive linear moves cut by a circular arc of
    `radius` [m] tangent to both legs (legs at right angles): frames within `radius` of
    the corner move onto the arc, by their distance along the legs. The arc passes the
    corner at radius·(√2 − 1) (CR) and leaves the first leg where it is radius·(1 − 1/√2)
    from both legs (where the deviation switches from the first leg to the second: CO)."""
    p = p.copy()
    tp = prog.targets.position
    lin = prog.motion == "linear"
    for j in range(1, len(tp) - 1):
        if not (lin[j] and lin[j + 1]):
            continue
        c = tp[j]
        d1 = (tp[j] - tp[j - 1]) / np.linalg.norm(tp[j] - tp[j - 1])
        d2 = (tp[j + 1] - tp[j]) / np.linalg.norm(tp[j + 1] - tp[j])
        for s_, sign, d in ((seg == j, -1.0, d1), (seg == j + 1, 1.0, d2)):
            along = (p[s_] - c) @ d
            near = np.abs(along) < radius
            idx = np.flatnonzero(s_)[near]
            # β ∈ [0, π/2]: π/4·(1 − |along|/radius) on the first leg, beyond on the second
            beta = np.pi / 4 * (1 + sign * np.abs(along[near]) / radius)
            p[idx] = (c + radius * (np.sin(beta) - 1)[:, None] * d1
                      + radius * (1 - np.cos(beta))[:, None] * d2)  # fmt: skip
    return p
