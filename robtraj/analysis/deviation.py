"""Path deviation of a measured TCP trajectory from the commanded path (paper section 4).

The commanded path is sampled densely (`commanded_path`); every measured point is
matched to its nearest reference samples with a k-d tree, the exact point-to-segment
distance (paper eq. 6) is taken on the intervals next to each candidate sample, and the
match is made *monotone in path progress* with a dynamic programme over the candidates,
so that a path that crosses itself or runs parallel to itself is not matched to the
wrong pass. The orientation at the foot point is slerped between the neighbouring
reference samples and compared by the single rotation angle (paper eq. 1–2).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Float
from scipy.spatial import cKDTree

from .._errors import UserError
from ..recording import Program
from ._quat import quat_conjugate, quat_multiply, rotation_angle, slerp

_EPS_LENGTH = 1e-12  # [m] intervals shorter than this are pure reorientations
_JUMP_MARGIN = 1e-6  # [m] a jump's nearest neighbour must be nearer than this
_SCAN_BLOCK = 1 << 15
#: [m] path progress around a turn in place within which a frame may be turning
TURN_WINDOW = 1e-4  # frames per compiled block of the monotone matching


@dataclasses.dataclass(frozen=True)
class ReferencePath:
    """The commanded TCP path, sampled; interval `r` joins samples `r` and `r + 1`.

    - `position` `(R, 3)` [m] and `quaternion_wxyz` `(R, 4)`: samples in the base frame.
    - `progress` `(R,)` [m]: cumulative path length `s` at each sample.
    - `interval_target` `(R-1,)`: program target index approached along each interval.
    - `interval_on_path` `(R-1,)`: True where the interval belongs to a "linear" move
      (a path the robot is meant to follow); False for "joint" moves, whose real TCP
      path is not a straight line, so deviations there are not path errors.
    """

    position: np.ndarray
    quaternion_wxyz: np.ndarray
    progress: np.ndarray
    interval_target: np.ndarray
    interval_on_path: np.ndarray

    @property
    def n_samples(self) -> int:
        return int(self.position.shape[0])


def commanded_path(program: Program, spacing: float) -> ReferencePath:
    """Sample the commanded TCP path of `program` every `spacing` metres (or closer).

    Consecutive targets are joined by straight lines with the orientation slerped along
    each move, the end points of each move are samples, and a move that only reorients
    (zero length) is one interval. Choose `spacing` at most half the distance the robot
    travels between two measurements (the paper asks for at least twice the density).

    **Arguments:**

    - `program`: the `Program`; `motion[j]` ("linear" or "joint") says how the robot
      moves from target `j-1` to target `j`; `motion[0]` is "start".
    - `spacing`: [m] largest distance between neighbouring samples, > 0.

    **Returns:** a `ReferencePath`.
    """
    pos = np.asarray(program.targets.position, np.float64)
    quat = np.asarray(program.targets.quaternion_wxyz, np.float64)
    if pos.ndim != 2 or pos.shape[0] < 2:
        raise UserError(
            f"the program has {0 if pos.ndim != 2 else pos.shape[0]} target(s); "
            "a commanded path needs at least two"
        )
    if not spacing > 0:
        raise UserError(f"path sampling spacing must be > 0 m, got {spacing!r}")
    motion = np.asarray(program.motion).astype(str)
    a, b = pos[:-1], pos[1:]
    length = np.linalg.norm(b - a, axis=1)
    n = np.maximum(1, np.ceil(length / spacing)).astype(np.int64)  # intervals per move
    seg = np.repeat(np.arange(len(n)), n)  # move index of each interval
    k = np.arange(seg.size) - np.repeat(np.cumsum(n) - n, n)
    t = k / n[seg]
    position = np.concatenate([a[seg] + t[:, None] * (b - a)[seg], pos[-1:]])
    q0, q1 = quat[:-1][seg], quat[1:][seg]
    # make consecutive targets use the same hemisphere so the samples are continuous
    quaternion = np.concatenate([slerp(q0, q1, t), quat[-1:]])
    flip = np.sum(quaternion[1:] * quaternion[:-1], axis=1) < 0
    sign = np.concatenate([[1.0], np.where(np.cumsum(flip) % 2 == 1, -1.0, 1.0)])
    quaternion = quaternion * sign[:, None]
    progress = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(position, axis=0), axis=1))])
    target = seg + 1
    on_path = motion[target] == "linear"
    return ReferencePath(position, quaternion, progress, target, on_path)


@dataclasses.dataclass(frozen=True)
class DeviationSummary:
    """Max, mean and RMS of the distance [m] and orientation error [rad] over `n` frames."""

    n: int
    distance_max: float
    distance_mean: float
    distance_rms: float
    orientation_max: float
    orientation_mean: float
    orientation_rms: float

    def to_json(self) -> dict[str, Any]:
        """Values in mm and degrees, keys with the unit."""
        return {
            "n_frames": self.n,
            "distance_max_mm": self.distance_max * 1e3,
            "distance_mean_mm": self.distance_mean * 1e3,
            "distance_rms_mm": self.distance_rms * 1e3,
            "orientation_max_deg": float(np.degrees(self.orientation_max)),
            "orientation_mean_deg": float(np.degrees(self.orientation_mean)),
            "orientation_rms_deg": float(np.degrees(self.orientation_rms)),
        }


@dataclasses.dataclass(frozen=True)
class DeviationResult:
    """Per-frame deviation of the measured path from a `ReferencePath` (NaN: frame unseen).

    - `distance` `(N,)` [m]: point-to-path distance (paper eq. 6).
    - `orientation_error` `(N,)` [rad]: single rotation angle to the slerped foot orientation.
    - `deviation` `(N, 3)` [m]: measured position minus foot point.
    - `foot` `(N, 3)`, `foot_quaternion_wxyz` `(N, 4)`: matched point on the commanded path.
    - `progress` `(N,)` [m]: path progress `s` of the foot point.
    - `interval` `(N,)`: matched reference interval (-1 for unseen frames).
    - `target` `(N,)`: program target index approached there (-1 for unseen frames).
    - `on_path` `(N,)`: matched to a "linear" move (deviation is a path error there).
    - `jumped` `(N,)`: the unconstrained nearest neighbour lies on another pass of the path
      (more than `jump_tolerance` away in progress) than the monotone match, and is nearer
      (by more than 1 µm; passes that repeat the same geometry are not jumps).
    - `held` `(N,)`: no admissible candidate was within `outlier_distance`; the frame
      keeps the previous frame's match.
    """

    distance: np.ndarray
    orientation_error: np.ndarray
    deviation: np.ndarray
    foot: np.ndarray
    foot_quaternion_wxyz: np.ndarray
    progress: np.ndarray
    interval: np.ndarray
    target: np.ndarray
    on_path: np.ndarray
    jumped: np.ndarray
    held: np.ndarray

    def summary(self, *, include_joint_moves: bool = False) -> DeviationSummary:
        """Max/mean/RMS over the seen frames on "linear" moves (all moves if asked)."""
        use = np.isfinite(self.distance)
        if not include_joint_moves:
            use &= self.on_path
        d, e = self.distance[use], self.orientation_error[use]
        if d.size == 0:
            raise UserError("no measured frame lies on a path segment of the program")
        return DeviationSummary(
            n=int(d.size),
            distance_max=float(d.max()),
            distance_mean=float(d.mean()),
            distance_rms=float(np.sqrt(np.mean(d**2))),
            orientation_max=float(e.max()),
            orientation_mean=float(e.mean()),
            orientation_rms=float(np.sqrt(np.mean(e**2))),
        )


def point_segment(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Foot parameter `t ∈ [0, 1]` and distance of `point` to segment `a`–`b` (paper eq. 6).

    The foot point is `a + t (b - a)`: the intersection of the segment's line with the
    plane through `point` normal to `n = b - a`, clamped to the segment. Broadcasts over
    leading axes; a degenerate segment gives `t = 0`.
    """
    n = b - a
    nn = np.sum(n * n, axis=-1)
    t = np.sum((point - a) * n, axis=-1) / np.where(nn > _EPS_LENGTH**2, nn, 1.0)
    t = np.clip(np.where(nn > _EPS_LENGTH**2, t, 0.0), 0.0, 1.0)
    foot = a + t[..., None] * n
    return t, np.linalg.norm(point - foot, axis=-1)


def path_deviation(
    reference: ReferencePath,
    measured_position: Float[np.ndarray, "frames 3"],
    measured_quaternion_wxyz: Float[np.ndarray, "frames 4"],
    *,
    monotone: bool = True,
    k: int = 4,
    outlier_distance: float = 0.05,
    backtrack: float = 1.0,
    jump_tolerance: float | None = None,
    turn_window: float = TURN_WINDOW,
    window: int | None = None,
) -> DeviationResult:
    """Match every measured pose to the commanded path and measure the deviation.

    **Arguments:**

    - `reference`: from `commanded_path`, sampled ≥ 2× as densely as the measurement.
    - `measured_position` `(N, 3)` [m], `measured_quaternion_wxyz` `(N, 4)`: measured TCP
      poses in the base frame, in time order; NaN rows (unseen frames) give NaN results.
    - `monotone`: constrain the match to be non-decreasing in path progress (the robot
      may dwell, not go back): each frame searches a forward window of intervals after
      the previous frame's match, so another pass of the path (a crossing, a parallel
      line, the next cycle) is never taken. Without it every frame takes its nearest
      interval among the k-d-tree candidates.
    - `k`: reference samples queried per frame in the k-d tree; each contributes its
      better adjacent interval as a candidate (unconstrained match, `jumped`, start and
      re-acquisition of the monotone match).
    - `outlier_distance`: [m] when the nearest interval in the forward window is farther
      than this, the nearest candidates ahead re-acquire the path; if none is nearer than
      this either, the frame keeps the previous match (`held`).
    - `backtrack`: tolerated step back, in reference intervals (noise at a dwell can move
      the foot point slightly backwards).
    - `turn_window`: [m] a foot point this near (in path progress) to a turn in place
      (consecutive moves that only reorient) is compared with the nearest orientation of
      the turn as well: the position cannot tell where in the turn the robot is, nor,
      within the measurement's noise, whether it has reached the turn. The default,
      `TURN_WINDOW`, is above an optical CMM's position noise; set it to yours.
    - `jump_tolerance`: [m] progress difference above which the unconstrained nearest
      neighbour counts as a jump to another pass; default 5 reference spacings.
    - `window`: intervals searched ahead of the previous match; default: enough for the
      largest step between two frames (at least 16).

    **Returns:** a `DeviationResult`.
    """
    pos = np.asarray(measured_position, np.float64)
    quat = np.asarray(measured_quaternion_wxyz, np.float64)
    if pos.shape[0] != quat.shape[0]:
        raise UserError(f"{pos.shape[0]} measured positions but {quat.shape[0]} orientations")
    n_int = reference.position.shape[0] - 1
    k = int(min(k, reference.position.shape[0]))
    seen = np.all(np.isfinite(pos), axis=1) & np.all(np.isfinite(quat), axis=1)
    idx_seen = np.flatnonzero(seen)
    s_ref = reference.progress
    if jump_tolerance is None:
        jump_tolerance = 5.0 * float(np.median(np.diff(s_ref))) if n_int else 0.0
    if window is None:
        spacing = float(np.median(np.diff(s_ref))) if n_int else 1.0
        window = int(max(16, np.ceil(2.0 * _largest_step(pos, idx_seen) / max(spacing, 1e-12)) + 8))
    out = _empty_result(pos.shape[0])
    match = _Match(reference, cKDTree(reference.position), k, outlier_distance, backtrack,
                   window, _turns(reference), turn_window)  # fmt: skip
    u_prev = jnp.asarray(0.0)  # the path's start; if the first frame is far, re-acquire
    for lo in range(0, idx_seen.size, _SCAN_BLOCK):
        rows = idx_seen[lo : lo + _SCAN_BLOCK]
        u_prev = match.block(pos[rows], quat[rows], u_prev, monotone, jump_tolerance, out, rows)
    return out


def _largest_step(pos: np.ndarray, idx_seen: np.ndarray, chunk: int = _SCAN_BLOCK) -> float:
    """The largest distance [m] between consecutive seen positions, `chunk` rows at a time."""
    step = 0.0
    for lo in range(0, max(idx_seen.size - 1, 0), chunk):
        p = pos[idx_seen[lo : lo + chunk + 1]]
        step = max(step, float(np.linalg.norm(np.diff(p, axis=0), axis=1).max(initial=0.0)))
    return step


def _empty_result(n_frames: int) -> DeviationResult:
    """A `DeviationResult` of `n_frames` unseen frames, filled block by block."""
    nan = functools.partial(np.full, fill_value=np.nan)
    return DeviationResult(
        distance=nan(n_frames),
        orientation_error=nan(n_frames),
        deviation=nan((n_frames, 3)),
        foot=nan((n_frames, 3)),
        foot_quaternion_wxyz=nan((n_frames, 4)),
        progress=nan(n_frames),
        interval=np.full(n_frames, -1, np.int64),
        target=np.full(n_frames, -1, np.int64),
        on_path=np.zeros(n_frames, bool),
        jumped=np.zeros(n_frames, bool),
        held=np.zeros(n_frames, bool),
    )


@dataclasses.dataclass(frozen=True)
class _Match:
    """Matches blocks of seen frames, in time order, to the commanded path; the monotone
    match carries over from one block to the next (`block` returns where it stands)."""

    reference: ReferencePath
    tree: cKDTree
    k: int
    outlier: float
    backtrack: float
    window: int
    turns: tuple[tuple[float, np.ndarray], ...]
    turn_window: float

    def candidates(self, p: np.ndarray):
        """Per frame, each of the `k` nearest samples' better adjacent interval: its index,
        foot parameter and distance [m]."""
        ref_p, n_int = self.reference.position, self.reference.n_samples - 1
        _, nearest = self.tree.query(p, k=self.k, workers=-1)
        nearest = nearest.reshape(p.shape[0], self.k)
        before = np.clip(nearest - 1, 0, n_int - 1)
        after = np.clip(nearest, 0, n_int - 1)
        tb, db = point_segment(p[:, None], ref_p[before], ref_p[before + 1])
        ta, da = point_segment(p[:, None], ref_p[after], ref_p[after + 1])
        use_after = da <= db
        return (
            np.where(use_after, after, before),
            np.where(use_after, ta, tb),
            np.where(use_after, da, db),
        )

    def block(self, p, q, u_prev, monotone, jump_tolerance, out: DeviationResult, rows):
        """Match seen frames `p` `(B, 3)` [m], `q` `(B, 4)` after the match `u_prev`, write
        them to `out` at `rows`; the match after the block's last frame."""
        ref = self.reference
        ref_p, n_int, s_ref = ref.position, ref.n_samples - 1, ref.progress
        cand, cand_t, cand_d = self.candidates(p)
        u = cand + cand_t  # fractional interval index: monotone in path progress
        best_free = np.argmin(cand_d, axis=1)
        i = np.arange(p.shape[0])
        if monotone:
            u_prev, chosen_u, held = _track(ref, p, u, cand_d, self.outlier, self.backtrack,
                                            self.window, u_prev)  # fmt: skip
            out.held[rows] = held
        else:
            chosen_u = u[i, best_free]
        interval = np.clip(np.floor(chosen_u).astype(np.int64), 0, n_int - 1)

        # exact foot point on the chosen interval; reorientations in place project by angle
        a, b = ref_p[interval], ref_p[interval + 1]
        t, dist = point_segment(p, a, b)
        qa, qb = ref.quaternion_wxyz[interval], ref.quaternion_wxyz[interval + 1]
        degenerate = np.sum((b - a) ** 2, axis=1) <= _EPS_LENGTH**2
        if np.any(degenerate):
            t = np.where(degenerate, _project_on_arc(qa, qb, q), t)
        foot = a + t[:, None] * (b - a)
        progress = s_ref[interval] + t * (s_ref[interval + 1] - s_ref[interval])

        free_int = np.clip(cand[i, best_free], 0, n_int - 1)
        free_t = cand_t[i, best_free]
        free_s = s_ref[free_int] + free_t * (s_ref[free_int + 1] - s_ref[free_int])
        # another pass that is really nearer (repeated identical passes are equally near)
        free_d = cand_d[i, best_free]
        out.jumped[rows] = (np.abs(free_s - progress) > jump_tolerance) & (
            free_d < dist - _JUMP_MARGIN
        )
        foot_q = np.array(slerp(qa, qb, t))
        err = np.array(rotation_angle(foot_q, q))
        for s_turn, members in self.turns:
            near = np.flatnonzero(np.abs(progress - s_turn) <= self.turn_window)
            if near.size:
                foot_q[near], err[near] = _nearest_on_turn(ref, members, q[near], foot_q[near],
                                                           err[near])  # fmt: skip
        out.distance[rows] = dist
        out.orientation_error[rows] = err
        out.deviation[rows] = p - foot
        out.foot[rows] = foot
        out.foot_quaternion_wxyz[rows] = foot_q
        out.progress[rows] = progress
        out.interval[rows] = interval
        out.target[rows] = ref.interval_target[interval]
        out.on_path[rows] = ref.interval_on_path[interval]
        return u_prev


def _turns(reference: ReferencePath) -> tuple[tuple[float, np.ndarray], ...]:
    """The turns in place of `reference`: per run of consecutive zero-length intervals,
    its path progress [m] and the intervals."""
    d = np.diff(reference.position, axis=0)
    still = np.flatnonzero(np.sum(d * d, axis=1) <= _EPS_LENGTH**2)
    runs = np.split(still, np.flatnonzero(np.diff(still) > 1) + 1) if still.size else []
    return tuple((float(reference.progress[r[0]]), r) for r in runs)


def _nearest_on_turn(reference: ReferencePath, members, q, foot_q, err):
    """Per measured orientation `q` `(F, 4)`: the nearer of the orientation `foot_q` (error
    `err` [rad]) and the nearest one on the arcs of the turn's intervals `members`."""
    for r in members:
        qa = np.broadcast_to(reference.quaternion_wxyz[r], q.shape)
        qb = np.broadcast_to(reference.quaternion_wxyz[r + 1], q.shape)
        on_arc = slerp(qa, qb, _project_on_arc(qa, qb, q))
        e = rotation_angle(on_arc, q)
        better = e < err
        foot_q, err = np.where(better[:, None], on_arc, foot_q), np.where(better, e, err)
    return foot_q, err


def _project_on_arc(qa: np.ndarray, qb: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Slerp parameter of the point on the arc `qa → qb` closest to `q` (in-place turns)."""
    rel_ab = quat_multiply(quat_conjugate(qa), qb)
    rel_aq = quat_multiply(quat_conjugate(qa), q)
    rel_ab = rel_ab * np.sign(rel_ab[:, :1] + (rel_ab[:, :1] == 0))
    rel_aq = rel_aq * np.sign(rel_aq[:, :1] + (rel_aq[:, :1] == 0))
    rv_ab = _log(rel_ab)
    rv_aq = _log(rel_aq)
    theta2 = np.sum(rv_ab**2, axis=1)
    t = np.sum(rv_ab * rv_aq, axis=1) / np.where(theta2 > 0, theta2, 1.0)
    return np.clip(np.where(theta2 > 0, t, 0.0), 0.0, 1.0)


def _log(q: np.ndarray) -> np.ndarray:
    v = np.linalg.norm(q[:, 1:], axis=1)
    angle = 2.0 * np.arctan2(v, q[:, 0])
    scale = np.where(v > 1e-15, angle / np.where(v > 1e-15, v, 1.0), 2.0)
    return q[:, 1:] * scale[:, None]


def _track(
    reference: ReferencePath,
    p: np.ndarray,
    cand_u: np.ndarray,
    cand_d: np.ndarray,
    outlier: float,
    backtrack: float,
    window: int,
    u_prev: jax.Array,
) -> tuple[jax.Array, np.ndarray, np.ndarray]:
    """Fractional interval index per frame of one block (at most `_SCAN_BLOCK` frames),
    non-decreasing from `u_prev` up to `backtrack` (dwell allowed); the match after the
    block, the indices and which frames were held.

    Each frame searches the intervals `[⌊u⌋ - backtrack, ⌊u⌋ + window)` ahead of the previous
    match for the nearest one; when even that is farther than `outlier`, the k-d-tree
    candidates ahead of the previous match re-acquire the path (the earliest of the
    nearly-nearest ones), else the frame keeps the previous match (`held`).
    """
    n_int = reference.position.shape[0] - 1
    b = int(np.ceil(backtrack))
    # a multiple of 8 (few distinct shapes, few compilations), at most the whole path
    width = int(min(8 * np.ceil((window + b + 1) / 8), n_int))
    # a fixed-size block (one compilation for any N), padded by repeating its final frame;
    # the padding comes after the block's last frame, so the carried match is taken there
    n = p.shape[0]
    pad = _SCAN_BLOCK - n

    def padded(x):
        return np.concatenate([x, np.repeat(x[-1:], pad, axis=0)]) if pad else x

    u, held = _track_scan(
        jnp.asarray(reference.position), padded(p), padded(cand_u), padded(cand_d), u_prev,
        outlier, float(backtrack), b, width,
    )  # fmt: skip
    u = np.asarray(u)[:n]
    return jnp.asarray(u[-1]), u, np.asarray(held)[:n]


@functools.partial(jax.jit, static_argnums=(7, 8))
def _track_scan(ref, p, cand_u, cand_d, u0, outlier, backtrack, b, width):
    n_int = ref.shape[0] - 1
    offsets = jnp.arange(width)

    def nearest_in_window(u_prev, x):
        lo = jnp.clip(jnp.floor(u_prev).astype(jnp.int32) - b, 0, n_int - width)
        a = jax.lax.dynamic_slice_in_dim(ref, lo, width + 1)
        seg_a, seg_b = a[:-1], a[1:]
        n = seg_b - seg_a
        nn = jnp.sum(n * n, axis=-1)
        ok = nn > _EPS_LENGTH**2
        t = jnp.sum((x - seg_a) * n, axis=-1) / jnp.where(ok, nn, 1.0)
        t = jnp.clip(jnp.where(ok, t, 0.0), 0.0, 1.0)
        d = jnp.linalg.norm(x - seg_a - t[:, None] * n, axis=-1)
        u = lo + offsets + t
        d = jnp.where(u >= u_prev - backtrack, d, jnp.inf)
        j = jnp.argmin(d)
        return u[j], d[j]

    def step(u_prev, inputs):
        x, cu, cd = inputs
        u_w, d_w = nearest_in_window(u_prev, x)
        ahead = cu >= u_prev - backtrack
        d_ahead = jnp.where(ahead, cd, jnp.inf)
        near = ahead & (cd <= jnp.min(d_ahead) + 0.5 * outlier)
        u_k = jnp.min(jnp.where(near, cu, jnp.inf))
        reacquire = (d_w > outlier) & (jnp.min(d_ahead) <= outlier)
        lost = (d_w > outlier) & ~reacquire
        u_new = jnp.where(reacquire, u_k, jnp.where(lost, u_prev, u_w))
        return u_new, (u_new, lost)

    _, (u, held) = jax.lax.scan(step, jnp.asarray(u0, p.dtype), (p, cand_u, cand_d))
    return u, held
