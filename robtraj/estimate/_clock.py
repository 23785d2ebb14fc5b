"""The offset between a robot controller's clock and the tracker's, found from the data.

The robot's joint log and the tracker stream are recorded on two clocks that differ by
seconds and often by their epoch (controller: UNIX time; tracker: time since power-on).
Both see the same motion: the tool's angular speed |ω| and the speed |v| of its origin
(the TCP) are the same in every frame of reference, so they need neither camera←base
nor the tool mount. From the tracker they come from per-frame tool poses (weighted
Procrustes of the constellation); from the robot through nominal forward kinematics of
the joint log. Their cross-correlation over every lag (FFT on a coarse grid) gives the
offset; a finer search around the peak gives it to a fraction of the tracker's frame
time, and a delete-one-block jackknife of that search its standard error.

Convention: ``robot_time = tracker_time + offset``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from scipy import ndimage, signal

from .._errors import UserError
from ..jax_ops import rotation_angle, weighted_procrustes
from ..model import RobotModel, forward_kinematics, pose_se3
from ..recording import Pose, finite_points
from ._poses import CHUNK, _chunk_length, _slab, fit_poses

#: [s] grid of the search over every lag
COARSE_STEP = 0.02
#: [s] span over which a speed is differenced (both clocks)
SPEED_SPAN = 0.01
#: the tool must move at least this much for a channel to count: |ω| [rad/s], |v| [m/s]
MIN_ACTIVITY = {"angular": 0.02, "linear": 0.005}
#: lowest correlation of the speeds at the best offset for the log to match the stream
#: (a log of the same run reaches 0.97–0.99 in simulation; another run's up to ~0.6)
MIN_CORRELATION = 0.8
#: share of the tracker's moving time the log must cover at an offset
MIN_OVERLAP = 0.5
#: [s] grid and Gaussian width on which the speeds are compared near the best offset
FINE_GRID, SMOOTHING = 1e-3, 0.02
#: time blocks of the jackknife for the standard error of the offset
BLOCKS = 8


@dataclasses.dataclass(frozen=True)
class ClockAlignment:
    """`offset` [s] (robot time − tracker time) with standard error `sigma` [s];
    `correlation` of the speed signals at the offset; `channels` used ("angular",
    "linear"); `overlap` the share of the tracker's span the log covers."""

    offset: float
    sigma: float
    correlation: float
    channels: tuple[str, ...]
    overlap: float


@dataclasses.dataclass(frozen=True)
class _Speeds:
    """Speed samples at the midpoints `time` [s] of pairs of poses: `angular` [rad/s]
    and `linear` [m/s], NaN where a pair is not usable."""

    time: np.ndarray
    angular: np.ndarray
    linear: np.ndarray


def _pair_speeds(time, quaternion_wxyz, position, span: float) -> _Speeds:
    """Speeds between each pose and the first one at least `span` later (NaN-aware)."""
    time = np.asarray(time, np.float64)
    lag = max(1, int(round(span / max(np.median(np.diff(time)), 1e-9))))
    t0, t1 = time[:-lag], time[lag:]
    q = jnp.asarray(quaternion_wxyz)
    angle = np.asarray(rotation_angle(q[:-lag], q[lag:]))
    dt = t1 - t0
    shift = np.linalg.norm(position[lag:] - position[:-lag], axis=1)
    return _Speeds(0.5 * (t0 + t1), angle / dt, shift / dt)


def tracker_speeds(
    time: np.ndarray,
    positions: np.ndarray,
    constellation: np.ndarray,
    span: float = SPEED_SPAN,
) -> _Speeds:
    """Tool speeds from the LED stream: per-frame poses of `constellation` `(M, 3)` [m,
    tool frame] fitted to `positions` `(N, M, 3)` [m, camera frame], unit weights."""
    fit = fit_poses(constellation, positions, finite_points(positions).astype(np.float64))
    return _pair_speeds(time, fit.quaternion_wxyz, fit.position, span)


def stream_speeds(time: np.ndarray, positions: np.ndarray, span: float = SPEED_SPAN) -> _Speeds:
    """Angular speed of the tool from the LED stream alone (no constellation): the rigid
    turn between each frame and the one `span` later, from the LEDs seen in both. The
    linear speed of an unknown tool point has no counterpart on the robot: NaN."""
    time = np.asarray(time, np.float64)
    lag = max(1, int(round(span / max(np.median(np.diff(time)), 1e-9))))
    n = time.size - lag
    size = _chunk_length(n, CHUNK)  # chunks of a few lengths: a few compiled kernels
    q = []
    for start in range(0, n, size):  # bounded memory on whole recordings
        a = _slab(positions[:n], start, size, 0, np.nan)
        b = _slab(positions[lag:], start, size, 0, np.nan)
        both = finite_points(a) & finite_points(b)
        fit = weighted_procrustes(jnp.asarray(a), jnp.asarray(b), jnp.asarray(both, np.float64))
        q.append(np.asarray(fit.quaternion_wxyz)[: min(size, n - start)])
    q = jnp.asarray(np.concatenate(q))
    angle = np.asarray(rotation_angle(jnp.broadcast_to(jnp.eye(4, dtype=q.dtype)[0], q.shape), q))
    dt = time[lag:] - time[:-lag]
    return _Speeds(0.5 * (time[lag:] + time[:-lag]), angle / dt, np.full(dt.shape, np.nan))


def tool_poses(robot: RobotModel, joints: np.ndarray, flange_from_tool: Pose | None) -> Pose:
    """base←tool `(K, ·)` by nominal forward kinematics of `joints` `(K, J)` [rad] (the
    flange where `flange_from_tool` is None)."""
    fft = jaxlie.SE3.identity() if flange_from_tool is None else pose_se3(flange_from_tool)
    pose = jax.jit(jax.vmap(lambda q: (forward_kinematics(robot, q) @ fft).wxyz_xyz))(
        jnp.asarray(joints, jnp.float64)
    )
    pose = np.asarray(pose)
    return Pose(pose[:, 4:], pose[:, :4])


def robot_speeds(
    robot: RobotModel,
    log_time: np.ndarray,
    joints: np.ndarray,
    flange_from_tool: Pose | None,
    span: float = SPEED_SPAN,
) -> _Speeds:
    """Tool speeds from the joint log through nominal forward kinematics (the tool origin
    at `flange_from_tool`, the flange if None)."""
    pose = tool_poses(robot, joints, flange_from_tool)
    return _pair_speeds(log_time, pose.quaternion_wxyz, pose.position, span)


def _binned(t: np.ndarray, v: np.ndarray, start: float, n: int, step: float) -> np.ndarray:
    """Mean of `v` in bins of `step` from `start` (`n` bins), NaN where a bin is empty."""
    ok = np.isfinite(v) & np.isfinite(t)
    k = np.floor((t[ok] - start) / step).astype(np.int64)
    inside = (k >= 0) & (k < n)
    k, vv = k[inside], v[ok][inside]
    total = np.bincount(k, vv, minlength=n)
    count = np.bincount(k, minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def _lagged_correlation(x: np.ndarray, y: np.ndarray):
    """Pearson correlation of `x` and `y` shifted by every lag k (``y[i + k]`` against
    ``x[i]``, k from −(len(x)−1) to len(y)−1) over the samples both have, with the
    number of such samples; NaN marks missing samples. All sums by FFT."""
    mx, my = np.isfinite(x), np.isfinite(y)
    xz, yz = np.where(mx, x, 0.0), np.where(my, y, 0.0)

    def corr(a, b):  # c[k] = Σ_i a[i] b[i + k]
        return signal.correlate(b, a, mode="full", method="fft")

    fx, fy = mx.astype(float), my.astype(float)
    n = corr(fx, fy)
    sx, sy = corr(xz, fy), corr(fx, yz)
    sxx, syy = corr(xz * xz, fy), corr(fx, yz * yz)
    sxy = corr(xz, yz)
    with np.errstate(invalid="ignore", divide="ignore"):
        nn = np.maximum(np.round(n), 1.0)
        cov = sxy - sx * sy / nn
        vx = sxx - sx * sx / nn
        vy = syy - sy * sy / nn
        spread = (vx > 1e-9 * np.abs(sxx)) & (vy > 1e-9 * np.abs(syy))
        r = np.where(spread, cov / np.sqrt(np.abs(vx * vy)), np.nan)
    lags = np.arange(-(x.size - 1), y.size)
    return lags, np.where(np.round(n) > 2, np.clip(r, -1.0, 1.0), np.nan), np.round(n)


def _active_channels(robot_side: _Speeds, tracker_side: _Speeds) -> tuple[str, ...]:
    out = []
    for ch, limit in MIN_ACTIVITY.items():
        a, b = getattr(robot_side, ch), getattr(tracker_side, ch)
        a, b = a[np.isfinite(a)], b[np.isfinite(b)]
        if a.size > 2 and b.size > 2 and np.std(a) > limit and np.std(b) > limit:
            out.append(ch)
    return tuple(out)


def _coarse(trk: _Speeds, rob: _Speeds, channels, step: float):
    """Best offset on the `step` grid over every lag: (offset, correlation, overlap)."""
    t0, r0 = float(np.nanmin(trk.time)), float(np.nanmin(rob.time))
    nt = int(np.ceil((np.nanmax(trk.time) - t0) / step)) + 1
    nr = int(np.ceil((np.nanmax(rob.time) - r0) / step)) + 1
    total, lags, counts = None, None, None
    for ch in channels:
        x = _binned(trk.time, getattr(trk, ch), t0, nt, step)
        y = _binned(rob.time, getattr(rob, ch), r0, nr, step)
        lags, r, n = _lagged_correlation(x, y)
        total = r if total is None else total + r
        counts = n
    score = total / len(channels)
    trk_bins = np.isfinite(_binned(trk.time, getattr(trk, channels[0]), t0, nt, step)).sum()
    overlap = counts / max(trk_bins, 1)
    score = np.where(overlap >= MIN_OVERLAP, score, np.nan)
    if not np.any(np.isfinite(score)):
        return None, float("nan"), float(np.nanmax(overlap, initial=0.0))
    k = int(np.nanargmax(score))
    return r0 - t0 + lags[k] * step, float(score[k]), float(overlap[k])


def _scores(trk: _Speeds, rob: _Speeds, channels, offsets: np.ndarray) -> np.ndarray:
    """Sum over `channels` of the correlation of the tracker's speeds with the robot's,
    interpolated at the tracker's sample times + each of `offsets`."""
    score = np.zeros(offsets.shape)
    for ch in channels:
        x, tx = getattr(trk, ch), trk.time
        y, ty = getattr(rob, ch), rob.time
        ty, y = ty[np.isfinite(y)], y[np.isfinite(y)]
        for i, off in enumerate(offsets):
            yi = np.interp(tx + off, ty, y, left=np.nan, right=np.nan)
            ok = np.isfinite(x) & np.isfinite(yi)
            if ok.sum() < 10 or np.std(x[ok]) == 0 or np.std(yi[ok]) == 0:
                score[i] = np.nan
            else:
                score[i] += np.corrcoef(x[ok], yi[ok])[0, 1]
    return score


def _fine(trk: _Speeds, rob: _Speeds, channels, centre: float, half: float, step: float):
    """Offset maximising the correlation of the speed channels within ±`half` of
    `centre`: a grid of ~20 offsets, then one of `step` around its best, refined by a
    parabola through the peak. None where the peak lies on the edge or is undefined."""
    coarse = max(step, half / 10)
    for grid_half, grid_step in ((half, coarse), (2 * coarse, step)):
        offsets = centre + np.arange(-grid_half, grid_half + grid_step / 2, grid_step)
        score = _scores(trk, rob, channels, offsets)
        if not np.any(np.isfinite(score)):
            return None
        k = int(np.nanargmax(score))
        if k == 0 or k == offsets.size - 1:
            return None
        centre = float(offsets[k])
    if not np.all(np.isfinite(score[k - 1 : k + 2])):
        return None
    a, b, c = score[k - 1 : k + 2]
    denom = a - 2 * b + c
    frac = 0.0 if denom == 0 else 0.5 * (a - c) / denom
    return float(offsets[k] + frac * step)


def _smoothed(s: _Speeds, step: float = FINE_GRID, width: float = SMOOTHING) -> _Speeds:
    """`s` on a uniform grid of `step` [s] (linear interpolation between samples, NaN
    across gaps of more than twice the median spacing), each channel then smoothed by a
    Gaussian of standard deviation `width` [s] (normalised where samples are missing).
    Both clocks' speeds pass the same filter, so the offset is not biased; the noise of
    single samples and the jitter of their time stamps no longer ripple the correlation
    as the offset moves across sample times."""
    grid = np.arange(float(np.nanmin(s.time)), float(np.nanmax(s.time)), step)
    out = {}
    for ch in ("angular", "linear"):
        v = getattr(s, ch)
        ok = np.isfinite(v) & np.isfinite(s.time)
        t, v = s.time[ok], v[ok]
        if t.size < 2:
            out[ch] = np.full(grid.shape, np.nan)
            continue
        k = np.clip(np.searchsorted(t, grid), 1, t.size - 1)
        near = (t[k] - t[k - 1]) <= 2 * np.median(np.diff(t))
        have = near & (grid >= t[0]) & (grid <= t[-1])
        on_grid = np.where(have, np.interp(grid, t, v), 0.0)
        sd = width / step
        weight = ndimage.gaussian_filter1d(have.astype(float), sd, mode="constant")
        total = ndimage.gaussian_filter1d(on_grid, sd, mode="constant")
        with np.errstate(invalid="ignore", divide="ignore"):
            out[ch] = np.where(weight > 0.5, total / weight, np.nan)
    return _Speeds(grid, out["angular"], out["linear"])


def align_clocks(trk: _Speeds, rob: _Speeds, *, fine_step: float = 2.5e-4) -> ClockAlignment:
    """The clock offset (robot − tracker) that makes the robot's tool speeds match the
    tracker's, over every lag; `UserError` when the tool does not move enough or no
    offset makes the log match the stream (a log of another run, or none overlapping)."""
    channels = _active_channels(rob, trk)
    if not channels:
        raise UserError(
            "the tool hardly moves in the tracker stream or the robot log, so the clocks "
            "cannot be aligned from the data; give the offset with --clock-offset"
        )
    offset, corr, overlap = _coarse(trk, rob, channels, COARSE_STEP)
    if offset is None or not corr >= MIN_CORRELATION:
        where = "" if offset is None else f" (best: {corr:.2f} at an offset of {offset:.3f} s)"
        raise UserError(
            "the robot log does not match the tracker stream at any clock offset: the "
            f"tool's speeds correlate below {MIN_CORRELATION}{where} or the log covers "
            f"less than {MIN_OVERLAP:.0%} of the stream; is it the log of this run?"
        )
    trk, rob = _smoothed(trk), _smoothed(rob)
    best = _fine(trk, rob, channels, offset, 2 * COARSE_STEP, fine_step)
    if best is None:
        raise UserError("the clock offset has no clear optimum near the coarse estimate")
    sigma = _block_sigma(trk, rob, channels, best, fine_step)
    return ClockAlignment(best, sigma, corr, channels, min(1.0, overlap))


def _block_sigma(trk: _Speeds, rob: _Speeds, channels, best: float, step: float) -> float:
    """Standard error of the offset by the delete-one-block jackknife over `BLOCKS` time
    blocks of the tracker stream: each block left out in turn, the offset found again
    from the rest (blocks differ in how much motion they hold, which the spread of
    per-block estimates would overstate). NaN where fewer than 3 refits find an optimum."""
    edges = np.linspace(np.nanmin(trk.time), np.nanmax(trk.time), BLOCKS + 1)
    found = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        keep = (trk.time < lo) | (trk.time >= hi)
        rest = _Speeds(trk.time[keep], trk.angular[keep], trk.linear[keep])
        est = _fine(rest, rob, channels, best, 0.01, step)
        if est is not None:
            found.append(est)
    n = len(found)
    if n < 3:
        return float("nan")
    return float(np.sqrt((n - 1) / n * np.sum((np.asarray(found) - np.mean(found)) ** 2)))


def clock_effects(robot_log) -> tuple[str, ...]:
    """``("time_offset",)`` for a robot log whose clock was aligned to the tracker's from
    the data (`robtraj attach`): what is left of the offset, a fraction of a frame time,
    still moves the TCP by speed × offset, so every fit estimates it as τ."""
    sigma = None if robot_log is None else robot_log.clock_offset_sigma
    return ("time_offset",) if sigma is not None and sigma != 0.0 else ()
