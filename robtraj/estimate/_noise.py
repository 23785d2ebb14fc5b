"""The noise of a recording: per-axis LED noise σ [m] as a function of the emission angle,
the distance and the LED, estimated from the whole recording (moving frames included),
independently of any robot or calibration model.

**Estimator.** The distance between two LEDs of one rigid tool does not change as the
tool moves, so its second difference over three consecutive frames,
``Δ²d_ij = d_ij(t−1) − 2 d_ij(t) + d_ij(t+1)``, is noise alone, up to the curvature of
slow systematic effects (an emission-angle bias changes a distance by micrometres from
one frame to the next, and the second difference removes its slope). For isotropic
per-axis noise independent between frames,
``E[(Δ²d_ij)²] = Σ_s c_s² (σ_i²(t+s) + σ_j²(t+s))`` with ``c = (1, −2, 1)``: linear in
the variances. The variance model is

    σ²(θ, r, k) = λ_k · Σ_ab v_ab h_a(θ) g_b(r)

with piecewise-linear hat functions h in the emission angle θ and g in the distance r
(camera frame origin to the LED), and a level λ_k per LED (count-weighted mean 1).
``v ≥ 0`` by non-negative least squares and λ by alternation, with the weights of
``Var (Δ²d)² = 2 E[(Δ²d)²]²`` (Gaussian noise) iterated. The relative standard error of
the mean variance comes from a jackknife over contiguous time blocks.

What it cannot see: noise correlated between consecutive frames (it is taken for
smaller than it is) and any error common to all LEDs of a frame (a rigid shift of the
tool, which is not noise of the LEDs).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float, Int
from scipy.optimize import nnls

from .._errors import UserError

#: hat functions over the emission angle (knots at evenly spaced quantiles of the angles seen)
ANGLE_KNOTS = 10
#: hat functions over the distance (uniform knots between its 0.5 % and 99.5 % quantiles)
DISTANCE_KNOTS = 3
#: frame triples used at most (evenly spaced over the recording)
MAX_TRIPLES = 8000
#: least variance of any knot, as a fraction of the mean variance of the observations
VARIANCE_FLOOR = 0.02
#: contiguous time blocks of the jackknife
BLOCKS = 8
#: a knot's curvature in a jackknife replicate below this fraction of the full one: not
#: determined without the left-out block
UNDETERMINED = 1e-9
#: below this per-axis σ [m] (1 nm, a thousandth of the best optical tracker's noise) the
#: LED positions carry no noise of their own: points computed from a 6-DOF pose, or
#: rounded to a rigid body, whose variances the model cannot tell
MIN_SIGMA = 1e-9
_C2 = np.array([1.0, 4.0, 1.0])  # squares of the second-difference coefficients
_BLOCK = 1 << 17  # frames per block of `NoiseModel.observation_variance`


class NoiseModel(eqx.Module):
    """Per-axis LED noise variance [m²] as a function of emission angle [rad], distance
    [m] and LED (see the module docstring).

    - `angle_knots` `(a,)` [rad], `distance_knots` `(b,)` [m]: where the variance table
      is given; outside, the end values hold.
    - `variance` `(a, b)` [m²]: per-axis variance at the knots for an LED of level 1.
    - `led_ids` `(m,)`, `led_level` `(m,)`: each LED's level (count-weighted mean 1).
    - `level_rel_se`: relative standard error of the model's mean variance (jackknife).
    - `n_samples`: pair second differences the model rests on.
    """

    angle_knots: Float[np.ndarray, " a"]
    distance_knots: Float[np.ndarray, " b"]
    variance: Float[np.ndarray, "a b"]
    led_ids: Int[np.ndarray, " leds"]
    led_level: Float[np.ndarray, " leds"]
    level_rel_se: float
    n_samples: int

    def variance_at(
        self,
        theta: Float[np.ndarray, "*#batch"] | float,
        distance: Float[np.ndarray, "*#batch"] | float,
        led: Int[np.ndarray, "*#batch"] | None = None,
    ) -> Float[np.ndarray, "*#batch"]:
        """Per-axis variance [m²] at emission angle `theta` [rad] and `distance` [m] for
        LED columns `led` (indices into `led_ids`; level 1 if None). NaN in → NaN out."""
        v = _bilinear(self.variance, self.angle_knots, self.distance_knots, theta, distance)
        if led is not None:
            v = v * self.led_level[led]
        return v

    def sigma_at(self, theta, distance, led=None):
        """Per-axis standard deviation [m]; arguments as `variance_at`."""
        return np.sqrt(self.variance_at(theta, distance, led))

    def observation_variance(
        self, positions: Float[np.ndarray, "frames leds 3"], theta: Float[np.ndarray, "frames leds"]
    ) -> Float[np.ndarray, "frames leds"]:
        """Per-axis variance [m²] of every observation of a recording whose LED columns
        are `led_ids` (positions in the camera frame [m], NaN where unseen): `variance_at`
        as one compiled kernel over blocks of `_BLOCK` frames."""
        n = positions.shape[0]
        th = np.zeros(positions.shape[:2]) if self.angle_knots.size == 1 else theta
        size = min(_BLOCK, n)
        out = np.empty(positions.shape[:2])
        args = (self.angle_knots, self.distance_knots, self.variance, self.led_level)
        for a in range(0, n, size):
            x, t = positions[a : a + size], th[a : a + size]
            if x.shape[0] < size:  # padded: one compilation for all blocks
                pad = size - x.shape[0]
                x = np.concatenate([x, np.full((pad, *x.shape[1:]), np.nan)])
                t = np.concatenate([t, np.full((pad, *t.shape[1:]), np.nan)])
            out[a : a + size] = np.asarray(_observation_variance(x, t, *args))[: n - a]
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary: the σ table [m] at the knots and the LED levels."""
        return {
            "kind": "pair_second_differences",
            "emission_angle_deg": np.rad2deg(self.angle_knots).tolist(),
            "distance_m": self.distance_knots.tolist(),
            "sigma_m": np.sqrt(self.variance).tolist(),
            "led_ids": self.led_ids.tolist(),
            "led_level": self.led_level.tolist(),
            "level_rel_se": self.level_rel_se,
            "n_samples": self.n_samples,
        }


def _locate(x, knots, xp=np):
    """Interval index and fraction of `x` between `knots` (clamped at the ends), in the
    array namespace `xp` (NumPy or `jax.numpy`)."""
    x = xp.asarray(x, float)
    k = knots.shape[0]
    if k == 1:
        return xp.zeros(x.shape, int), xp.zeros(x.shape)
    xc = xp.clip(x, knots[0], knots[-1])
    # the last knot at or below xc (the one before the last at the end): a comparison
    # per knot, where a binary search over a few knots is slow in XLA
    i = sum((xc >= knots[m]).astype(int) for m in range(1, k - 1)) + xp.zeros(x.shape, int)
    return i, (xc - knots[i]) / (knots[i + 1] - knots[i])


def _bilinear(table, ka, kb, x, y, xp=np):
    """Bilinear interpolation of `table` `(a, b)` at (`x`, `y`) between the knots `ka`,
    `kb` (end values beyond them; NaN where `x` or `y` is not finite)."""
    x, y = xp.broadcast_arrays(xp.asarray(x, float), xp.asarray(y, float))
    i, u = _locate(xp.nan_to_num(x), ka, xp)
    j, w = _locate(xp.nan_to_num(y), kb, xp)
    i1 = xp.minimum(i + 1, ka.shape[0] - 1)
    j1 = xp.minimum(j + 1, kb.shape[0] - 1)
    v = (
        (1 - u) * (1 - w) * table[i, j]
        + u * (1 - w) * table[i1, j]
        + (1 - u) * w * table[i, j1]
        + u * w * table[i1, j1]
    )
    return xp.where(xp.isfinite(x) & xp.isfinite(y), v, xp.nan)


@jax.jit
def _observation_variance(positions, theta, angle_knots, distance_knots, table, level):
    """`NoiseModel.observation_variance` of one block of frames (JAX)."""
    dist = jnp.sqrt(positions[..., 0] ** 2 + positions[..., 1] ** 2 + positions[..., 2] ** 2)
    return _bilinear(table, angle_knots, distance_knots, theta, dist, jnp) * level


def _hats(x: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """Hat-function values `(*x.shape, K)` at `x`."""
    i, u = _locate(x, knots)
    out = np.zeros(x.shape + (knots.size,))
    np.put_along_axis(out, i[..., None], (1 - u)[..., None], -1)
    if knots.size > 1:
        np.put_along_axis(out, (i + 1)[..., None], u[..., None], -1)
    return out


def estimate_noise(
    positions: Float[np.ndarray, "frames leds 3"],
    theta: Float[np.ndarray, "frames leds"] | None,
    led_ids: Int[np.ndarray, " leds"],
    *,
    max_triples: int = MAX_TRIPLES,
) -> NoiseModel:
    """The noise model of one rigid tool's LEDs (module docstring).

    **Arguments:** `positions` in the camera frame [m] (NaN where unseen), `theta` the
    emission angle [rad] of each observation (None when the LED normals are unknown: the
    model then depends on distance and LED only), `led_ids` the columns' LED ids.

    Raises `UserError` when fewer than 10 triples of consecutive frames see two LEDs, or
    when the pair distances show no noise (σ below `MIN_SIGMA`).
    """
    pos = np.asarray(positions, float)
    n, m = pos.shape[:2]
    has_angle = theta is not None and np.any(np.isfinite(theta))
    th = np.asarray(theta, float) if has_angle else np.zeros((n, m))
    seen = np.all(np.isfinite(pos), -1) & np.isfinite(th)
    trip = seen[:-2] & seen[1:-1] & seen[2:]
    cand = pick_triples(trip.sum(1) >= 2, max_triples)
    idx = cand[:, None] + np.arange(3)  # (T, 3) frames of each triple
    return noise_from_triples(pos[idx], th[idx], trip[cand], led_ids, has_angle=bool(has_angle))


def pick_triples(usable: np.ndarray, max_triples: int = MAX_TRIPLES) -> np.ndarray:
    """The first frames of the triples the model uses: of the frames t where `usable`
    `(N - 2,)` (two LEDs seen in t, t+1 and t+2), at most `max_triples` evenly spaced.
    Raises `UserError` when there are fewer than 10."""
    cand = np.flatnonzero(usable)
    if cand.size < 10:
        raise UserError(
            "fewer than 10 runs of three consecutive frames see two LEDs: the noise of the "
            "recording cannot be estimated"
        )
    if cand.size > max_triples:
        cand = cand[np.round(np.linspace(0, cand.size - 1, max_triples)).astype(np.int64)]
    return cand


def noise_from_triples(
    positions: Float[np.ndarray, "triples 3 leds 3"],
    theta: Float[np.ndarray, "triples 3 leds"],
    seen: Bool[np.ndarray, "triples leds"],
    led_ids: Int[np.ndarray, " leds"],
    *,
    has_angle: bool,
) -> NoiseModel:
    """`estimate_noise` from the frame triples it uses (`pick_triples`): their
    `positions` [m] and emission angles `theta` [rad] (zeros without `has_angle`), and
    which LEDs are `seen` (with an angle) in all three frames of each."""
    m = positions.shape[2]
    n_triples = positions.shape[0]
    p = np.where(seen[:, None, :, None], positions, 0.0)  # (T, 3, m, 3)
    s = seen.astype(float)  # (T, m) LED seen in all three frames
    dist = np.linalg.norm(positions, axis=-1)
    ang = theta
    ok = np.broadcast_to(s[:, None, :] > 0, dist.shape)

    ka = (
        np.unique(np.quantile(ang[ok], np.linspace(0.001, 0.999, ANGLE_KNOTS)))
        if has_angle
        else np.zeros(1)
    )
    lo, hi = np.quantile(dist[ok], [0.005, 0.995])
    kb = np.linspace(lo, hi, DISTANCE_KNOTS) if hi - lo > 1e-3 else np.array([0.5 * (lo + hi)])
    basis = (
        _hats(np.where(ok, ang, 0.0), ka)[..., :, None]
        * _hats(np.where(ok, dist, lo), kb)[..., None, :]
    )
    # F[t, k] = Σ_s c_s² φ(θ_k(t+s), r_k(t+s)): the variance features of LED k's triple
    feat = np.einsum("s,tskab->tkab", _C2, basis).reshape(n_triples, m, -1) * s[..., None]
    del basis

    # squared second differences of every pair distance, on the pairs seen throughout
    y = np.concatenate(
        [
            (d[:, 0] - 2 * d[:, 1] + d[:, 2]) ** 2
            for c in range(0, n_triples, 1024)
            for d in [
                np.linalg.norm(p[c : c + 1024, :, :, None] - p[c : c + 1024, :, None], axis=-1)
            ]
        ]
    )  # (T, m, m)
    pair = s[:, :, None] * s[:, None, :] * (1 - np.eye(m))[None]
    y = y * pair
    del p

    level = np.ones(m)
    w = pair.copy()
    v = np.zeros(feat.shape[-1])
    for _ in range(5):
        a = feat * level[None, :, None]
        v = _nnls_normal(*_normal_v(a, w, y))
        g = feat @ v  # (T, m) variance contribution of each LED at level 1
        level = _solve_level(g, w, y, s, level)
        e = (level * g)[:, :, None] + (level * g)[:, None, :]
        w = np.where(pair > 0, 1.0 / np.maximum(e, 1e-30) ** 2, 0.0)
    # rescale so that the LEDs' levels average to 1, weighted by observation count
    mean_level = float(np.sum(level * s.sum(0)) / s.sum())
    level, v = level / mean_level, v * mean_level

    # jackknife over contiguous time blocks: the mean variance of the observations
    a = feat * level[None, :, None]
    centre_mean = np.einsum("tkf,tk->f", a, s) / s.sum() / _C2.sum()
    block = np.minimum((np.arange(n_triples) * BLOCKS) // n_triples, BLOCKS - 1)
    parts = [_normal_v(a[block == b], w[block == b], y[block == b]) for b in range(BLOCKS)]
    h_all = sum(q[0] for q in parts)
    r_all = sum(q[1] for q in parts)
    means = np.array(
        [centre_mean @ _held_out(h_all - hb, r_all - rb, np.diag(h_all), v) for hb, rb in parts]
    )
    full = float(centre_mean @ v)
    if not full >= MIN_SIGMA**2:
        raise UserError(
            f"the distances between the LEDs do not vary from frame to frame (σ "
            f"{np.sqrt(max(full, 0.0)):.1e} m): the positions carry no LED noise of their own "
            "(points computed from a 6-DOF pose?), so no noise model can be estimated"
        )
    # a knot the data barely reach may come out at zero; no LED is noiseless
    v = np.maximum(v, VARIANCE_FLOOR * full)
    rel_se = float(np.sqrt((BLOCKS - 1) / BLOCKS * np.sum((means - means.mean()) ** 2)) / full)
    return NoiseModel(
        angle_knots=ka,
        distance_knots=kb,
        variance=v.reshape(ka.size, kb.size),
        led_ids=np.asarray(led_ids),
        led_level=level,
        level_rel_se=rel_se,
        n_samples=int(pair.sum() // 2),
    )


def _normal_v(a, w, y):
    """Normal equations of y_ij ≈ (a_i + a_j)·v over the pairs i < j (weights w)."""
    f = a.shape[-1]
    sw = w.sum(-1)  # (T, m)
    flat = a.reshape(-1, f)
    h = flat.T @ (flat * sw.reshape(-1, 1)) + flat.T @ (w @ a).reshape(-1, f)
    r = flat.T @ (w * y).sum(-1).reshape(-1)
    return h, r


def _nnls_normal(h: np.ndarray, r: np.ndarray) -> np.ndarray:
    """argmin_{v ≥ 0} of the quadratic with normal equations ``h v = r``."""
    scale = np.sqrt(np.maximum(np.diag(h), 1e-300))
    hs = h / scale[:, None] / scale[None, :] + 1e-10 * np.eye(h.shape[0])
    chol = np.linalg.cholesky(hs)  # hs = L Lᵀ
    z = np.linalg.solve(chol, r / scale)
    x, _ = nnls(chol.T, z, maxiter=50 * h.shape[0])
    return x / scale


def _held_out(h: np.ndarray, r: np.ndarray, full_diag: np.ndarray, v: np.ndarray) -> np.ndarray:
    """`_nnls_normal` of a jackknife replicate (normal equations ``h v = r`` without one
    block): a variance knot that only the left-out block reaches (its curvature below
    `UNDETERMINED` of the full one) is not determined by the rest and stays at the full
    fit's value `v`; the others are solved for with it held there."""
    held = np.diag(h) <= UNDETERMINED * full_diag
    out = v.copy()
    if np.all(held):
        return out
    free = ~held
    rhs = r[free] - h[np.ix_(free, held)] @ v[held]
    out[free] = _nnls_normal(h[np.ix_(free, free)], rhs)
    return out


def _solve_level(g, w, y, s, level):
    """Per-LED levels λ of y_ij ≈ λ_i g_i + λ_j g_j (weights w), kept in [0.1, 10]."""
    sw = w.sum(-1)
    h = np.diag(np.einsum("ti,ti->i", sw, g * g)) + np.einsum("ti,tij,tj->ij", g, w, g)
    r = np.einsum("ti,ti->i", g, (w * y).sum(-1))
    seen = s.sum(0) > 0
    out = level.copy()
    hh = h[np.ix_(seen, seen)]
    out[seen] = np.linalg.solve(hh + 1e-12 * np.trace(hh) * np.eye(hh.shape[0]), r[seen])
    return np.clip(out, 0.1, 10.0)


def noise_and_variance(
    positions: Float[np.ndarray, "frames leds 3"],
    theta: Float[np.ndarray, "frames leds"] | None,
    led_ids: Int[np.ndarray, " leds"],
) -> tuple[NoiseModel, Float[np.ndarray, "frames leds"]]:
    """`estimate_noise` of one rigid tool's LEDs and the per-axis variance [m²] it gives
    every observation (NaN where unseen); an observation without an emission angle (its
    frame has no pose) gets the variance at the median angle."""
    have_angle = theta is not None and bool(np.any(np.isfinite(theta)))
    model = estimate_noise(positions, theta if have_angle else None, led_ids)
    th = np.asarray(theta, float) if have_angle else np.zeros(positions.shape[:2])
    fill = float(np.nanmedian(th)) if have_angle else 0.0
    return model, model.observation_variance(positions, np.where(np.isfinite(th), th, fill))
