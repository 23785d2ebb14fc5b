"""Weighted rigid fit (no scale) of a constellation to measured points: Horn's method."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._quaternion import rotation_rows


class RigidFit(eqx.Module):
    """Result of `weighted_procrustes`, one row per frame.

    - `quaternion_wxyz`: `(frames, 4)` rotation R with ``measured ≈ R · model + position``
      (maps the model frame, e.g. `tool`, into the measurement frame, e.g. `camera`), unit
      quaternion w, x, y, z with ``w >= 0``; NaN where not `valid`.
    - `position`: `(frames, 3)` translation [m, the unit of the inputs]; NaN where not
      `valid`.
    - `rms`: `(frames,)` weighted residual RMS ``sqrt(Σ w |r|² / Σ w)`` [m]; NaN where not
      `valid`.
    - `n_used`: `(frames,)` number of LEDs with weight > 0 and finite measurement.
    - `valid`: `(frames,)` at least 3 LEDs used and the geometry is not (nearly) collinear.
    - `condition`: `(frames,)` in [0, 1]: the smaller of (a) the ratio e2/e1 of the
      second to the largest eigenvalue of the weighted model scatter and (b) the
      relative gap (λ1 - λ2)/λ1 of the two largest eigenvalues of Horn's matrix. Near 0
      means (nearly) collinear LEDs, where the rotation about the line is undetermined.
      Exact to first order near 0, where it decides `valid`; for well-spread LEDs (a)
      may be a few per cent low and (b) is a lower bound. No gradient.
    """

    quaternion_wxyz: Float[Array, "frames 4"]
    position: Float[Array, "frames 3"]
    rms: Float[Array, " frames"]
    n_used: Int[Array, " frames"]
    valid: Bool[Array, " frames"]
    condition: Float[Array, " frames"]


def collinear_threshold(dtype) -> float:
    """`condition` below which a fit is flagged invalid: ``sqrt(eps)`` of the dtype.

    With the eigenvalue ratio ``e2/e1 < sqrt(eps)`` the LEDs lie within a relative
    distance ``eps**0.25`` of a line (1.2e-4 in float64, e.g. 12 µm on a 0.1 m line;
    0.019 in float32), and the eigenvector of Horn's matrix would lose more than half of
    the digits (its error is ~eps / relative gap).
    """
    return float(np.sqrt(np.finfo(dtype).eps))


def weighted_procrustes(
    model: Float[Array, "leds 3"] | Float[Array, "frames leds 3"],
    measured: Float[Array, "frames leds 3"],
    weights: Float[Array, "frames leds"],
) -> RigidFit:
    """Weighted least-squares rigid transform per frame: ``measured ≈ R · model + t``.

    Minimises ``Σ_k w_k |R p_k + t - y_k|²`` over proper rotations R (det +1, never a
    reflection) and translations t, in closed form with Horn's unit-quaternion method:
    the rotation is the eigenvector of the largest eigenvalue of a symmetric 4x4 matrix
    N built from the weighted centred cross-covariance. That eigenvalue is found by
    Newton's method on the characteristic quartic of N (QCP: Theobald 2005, Liu et al.
    2010) from an upper bound, so it converges monotonically; the eigenvector is the
    best-conditioned column of the adjugate of ``N - λ I``. No eigen-solver or SVD,
    whole-array and branch-free; the weighted moments are two matrix products per block
    of frames, the residuals one more. Exact least-squares solution, so it also eliminates
    per-frame poses in a bundle adjustment. Differentiable w.r.t. `model`, `measured`
    and `weights` (the last Newton step carries the implicit derivative of λ, which
    exists for every valid frame; `condition` carries no gradient).

    **Arguments:**

    - `model`: `(leds, 3)` or `(frames, leds, 3)` points in the model frame (e.g. the
      constellation in the `tool` frame) [m].
    - `measured`: `(frames, leds, 3)` measured points (e.g. in the `camera` frame) [m];
      may be NaN where the weight is 0 (unseen LEDs).
    - `weights`: `(frames, leds)` non-negative weights [any unit]; 0 where unseen.
      Non-finite measurements or weights count as weight 0; NaN there reaches neither
      the values nor the gradients.

    **Returns:**

    A `RigidFit`. Frames with fewer than 3 used LEDs, or with (nearly) collinear used
    LEDs (`condition` below `collinear_threshold(dtype)`), get ``valid=False`` and NaN
    pose and rms.

    Inputs of up to one block (4096 frames) share one compiled kernel; longer ones are
    compiled per number of frames, like any jitted function (callers with varying
    lengths pad them to a few, as `robtraj.estimate` does for its chunks).
    """
    if measured.ndim != 3 or measured.shape[-1] != 3:
        raise ValueError(f"measured must be (frames, leds, 3), got {measured.shape}")
    if model.shape[-2:] != measured.shape[-2:] or model.ndim not in (2, 3):
        raise ValueError(f"model {model.shape} does not match measured {measured.shape}")
    if model.ndim == 3 and model.shape[0] != measured.shape[0]:
        raise ValueError(f"model {model.shape} does not match measured {measured.shape}")
    if weights.shape != measured.shape[:2]:
        raise ValueError(f"weights {weights.shape} do not match measured {measured.shape}")
    dtype = jnp.result_type(model, measured, weights)
    model, measured, weights = model.astype(dtype), measured.astype(dtype), weights.astype(dtype)
    n = measured.shape[0]
    if n >= _BLOCK:
        return _weighted_procrustes(model, measured, weights)
    # Fewer frames than a block: padded to one block (weight 0: invalid frames, cut off
    # again), so short inputs of any length reuse one compiled kernel.

    def pad(a):
        return jnp.pad(a, [(0, _BLOCK - n)] + [(0, 0)] * (a.ndim - 1))

    if model.ndim == 3:
        model = pad(model)
    fit = _weighted_procrustes(model, pad(measured), pad(weights))
    return jax.tree.map(lambda a: a[:n], fit)


# Newton steps on the deflated cubic (λ2, for the gap) and on the scatter's cubic; from
# the upper bound the iterates decrease monotonically to the root.
_STEPS_GAP = 8
_STEPS_SCATTER = 8
# At most this many Newton steps on the quartic (λ1) from sqrt(3)·|S|_F: a block stops
# when all its frames have converged, after ~5-12 steps for well-fitting frames; a
# mirror-image fit with a small eigen-gap (1e-4 .. 1e-8) needs up to ~30.
_STEPS_TOP = 40

# Frames per block of the kernel: the passes over a block's (frames, leds, 3) arrays
# then run in cache instead of main memory.
_BLOCK = 4096

_HP = jax.lax.Precision.HIGHEST  # no reduced-precision matmuls (GPU float32)


@jax.jit
def _weighted_procrustes(model: Array, measured: Array, weights: Array) -> RigidFit:
    n = measured.shape[0]
    size = min(n, _BLOCK)
    count = -(-n // size)
    # Blocks cut from the inputs in place (no padded copy); the last one ends at the last
    # frame and overlaps the one before it, whose frames it fits again.
    starts = jnp.minimum(jnp.arange(count) * size, n - size)

    def fit(start):
        def cut(a):
            return jax.lax.dynamic_slice_in_dim(a, start, size)

        return _fit_block(model if model.ndim == 2 else cut(model), cut(measured), cut(weights))

    out = jax.lax.map(fit, starts)
    rest = n - (count - 1) * size  # frames of the last block not in the one before

    def join(a):
        if rest == size:
            return a.reshape(n, *a.shape[2:])
        return jnp.concatenate([a[:-1].reshape(-1, *a.shape[2:]), a[-1, size - rest :]])

    return jax.tree.map(join, out)


def _fit_block(model: Array, measured: Array, weights: Array) -> RigidFit:
    dtype = measured.dtype
    finite = jnp.all(jnp.isfinite(measured), axis=-1) & jnp.all(jnp.isfinite(model), axis=-1)
    used = (weights > 0) & jnp.isfinite(weights) & finite  # (frames, leds)
    # double-where: masked entries are made safe before any arithmetic.
    w = jnp.where(used, weights, 0.0)
    y = jnp.where(used[..., None], measured, 0.0)
    n_used = jnp.sum(used, axis=1)
    if model.ndim == 2:
        (p_bar, y_bar, c, s), mean_square = _moments_shared(model, y, w)
    else:
        (p_bar, y_bar, c, s), mean_square = _moments_per_frame(model, y, w, used)
    q, valid, condition = _horn_rotation(c, s, n_used)
    # rotation entries as separate arrays: XLA fuses them into the translation
    r = rotation_rows(*q)
    t = [y_bar[a] - sum(r[a][b] * p_bar[b] for b in range(3)) for a in range(3)]
    ms = mean_square(r, t)
    # double-where: sqrt has an infinite derivative at a perfect fit.
    rms = jnp.where(ms > 0, jnp.sqrt(jnp.where(ms > 0, ms, 1.0)), 0.0)
    nan = jnp.array(jnp.nan, dtype)
    return RigidFit(
        jnp.where(valid[:, None], jnp.stack(q, axis=-1), nan),
        jnp.where(valid[:, None], jnp.stack(t, axis=-1), nan),
        jnp.where(valid, rms, nan),
        n_used,
        valid,
        jax.lax.stop_gradient(condition),
    )


def _moments_shared(model, y, w):
    """Weighted centred moments for one constellation `model` (leds, 3) shared by all
    frames, as lists of `(frames,)` arrays, and the weighted mean square residual of a
    pose (rotation rows `r`, translation `t`).

    All moments are linear in the weights and in ``w · y``, so they are matrix products
    with constant matrices built from the model: two GEMMs over all frames, the residuals
    one more and a matrix-vector product. They are uncentred; the model is shifted to its
    own centre first, and the measured points are centred by the first moment, so the
    cancellation in ``Σ w p yᵀ - p̄ Σ w yᵀ`` costs a factor |y| / |y - ȳ| (~15 for a
    0.1 m tool at 1.5 m): ~1e-14 in float64, and in float32 no more than the rounding of
    the measured points themselves.
    """
    n, m, _ = y.shape
    dtype = y.dtype
    ok_m = jnp.all(jnp.isfinite(model), axis=-1)
    p0 = jnp.where(ok_m[:, None], model, 0.0)
    origin = jnp.sum(p0, axis=0) / jnp.maximum(jnp.sum(ok_m), 1)
    p = jnp.where(ok_m[:, None], p0 - origin, 0.0)  # (leds, 3)
    eye = jnp.eye(3, dtype=dtype)
    # w @ [1 | p | p pᵀ]: zeroth, first and second model moments
    pm = jnp.concatenate(
        [jnp.ones((m, 1), dtype), p, (p[:, :, None] * p[:, None, :]).reshape(m, 9)], axis=1
    )
    mom_p = jnp.matmul(w, pm, precision=_HP)
    # (w y)_flat @ K, K[(m, j'), j] = δ(j', j) and K[(m, j'), (i, j)] = p[m, i] δ(j', j):
    # Σ_m w y_mj and Σ_m w p_mi y_mj
    k = jnp.concatenate(
        [jnp.tile(eye, (m, 1)), (eye[None, :, None, :] * p[:, None, :, None]).reshape(m * 3, 9)],
        axis=1,
    )
    wy = (w[..., None] * y).reshape(n, m * 3)
    mom_y = jnp.matmul(wy, k, precision=_HP)
    wsum = mom_p[:, 0]
    inv = 1.0 / jnp.where(wsum > 0, wsum, 1.0)
    p_bar = [mom_p[:, 1 + a] * inv for a in range(3)]
    y_bar = [mom_y[:, a] * inv for a in range(3)]
    c = [[mom_p[:, 4 + 3 * a + b] * inv - p_bar[a] * p_bar[b] for b in range(3)] for a in range(3)]
    s = [[mom_y[:, 3 + 3 * a + b] * inv - p_bar[a] * y_bar[b] for b in range(3)] for a in range(3)]
    # [R_flat | t] @ Q, Q[(i, j), (m, i')] = p[m, j] δ(i, i') and Q[i, (m, i')] = δ(i, i'):
    # R p_m + t for all LEDs
    q_mat = jnp.concatenate(
        [(eye[:, None, None, :] * p.T[None, :, :, None]).reshape(9, m * 3), jnp.tile(eye, (1, m))]
    )
    w3 = jnp.repeat(w, 3, axis=1)

    def mean_square(r, t):
        t = [t[a] + sum(r[a][b] * origin[b] for b in range(3)) for a in range(3)]
        rt = jnp.stack([r[a][b] for a in range(3) for b in range(3)] + t, axis=-1)
        res = y.reshape(n, m * 3) - jnp.matmul(rt, q_mat, precision=_HP)
        return jnp.matmul(w3 * res * res, jnp.ones(m * 3, dtype), precision=_HP) * inv

    p_bar = [p_bar[a] + origin[a] for a in range(3)]
    return (p_bar, y_bar, c, s), mean_square


def _moments_per_frame(model, y, w, used):
    """Weighted centred moments for a constellation per frame, `model` (frames, leds, 3),
    as lists of `(frames,)` arrays, and the weighted mean square residual of a pose."""
    wsum = jnp.sum(w, axis=1)
    wn = w / jnp.where(wsum > 0, wsum, 1.0)[:, None]
    p = jnp.where(used[..., None], model, 0.0)
    p_bar = jnp.sum(wn[..., None] * p, axis=1)
    y_bar = jnp.sum(wn[..., None] * y, axis=1)
    pc = jnp.where(used[..., None], p - p_bar[:, None], 0.0)
    yc = jnp.where(used[..., None], y - y_bar[:, None], 0.0)
    wpc = wn[..., None] * pc
    c = jnp.einsum("fmi,fmj->fij", wpc, pc, precision=_HP)
    s = jnp.einsum("fmi,fmj->fij", wpc, yc, precision=_HP)

    def mean_square(r, t):
        r = jnp.stack([jnp.stack(row, axis=-1) for row in r], axis=-2)
        res = y - jnp.einsum("fij,fmj->fmi", r, p, precision=_HP) - jnp.stack(t, axis=-1)[:, None]
        return jnp.sum(wn * jnp.sum(jnp.where(used[..., None], res, 0.0) ** 2, axis=-1), axis=1)

    moments = (
        [p_bar[:, a] for a in range(3)],
        [y_bar[:, a] for a in range(3)],
        [[c[:, a, b] for b in range(3)] for a in range(3)],
        [[s[:, a, b] for b in range(3)] for a in range(3)],
    )
    return moments, mean_square


def _horn_rotation(c, s, n_used) -> tuple[list[Array], Array, Array]:
    """Quaternion (w >= 0, as four arrays), validity and `condition` per frame from the
    weighted model scatter `c` and cross-covariance `s` (3x3 nested lists of arrays)."""
    dtype = c[0][0].dtype
    tol = collinear_threshold(dtype)
    model_ratio = _second_to_first(jax.lax.stop_gradient(c))
    # Scale S to unit Frobenius norm (the eigenvector is scale-invariant). The roots of
    # N's trace-free quartic have squares summing to |N|_F² = -2 c2 (= 4 after scaling),
    # so they are at most sqrt(-1.5 c2) (Laguerre-Samuelson): the start of Newton.
    scale = jnp.sqrt(sum(s[a][b] * s[a][b] for a in range(3) for b in range(3)))
    ok_scale = scale > jnp.finfo(dtype).tiny
    pre = (n_used >= 3) & ok_scale & (model_ratio > tol)
    inv_scale = 1.0 / jnp.where(ok_scale, scale, 1.0)
    # Benign S for frames that are invalid already: distinct eigenvalues of N, so every
    # step below and its derivative stay finite.
    benign = ((1.0, 0.0, 0.0), (0.0, 0.5, 0.0), (0.0, 0.0, 0.25))
    s = [[jnp.where(pre, s[a][b] * inv_scale, benign[a][b]) for b in range(3)] for a in range(3)]

    horn = _horn_matrix(s)
    # characteristic polynomial det(N - λI) = λ⁴ + c2 λ² + c1 λ + c0 (trace N = 0)
    c2 = -2.0 * sum(s[a][b] * s[a][b] for a in range(3) for b in range(3))
    c1 = -8.0 * _det3(s)
    c0 = _det4(horn)
    sc2, sc1, sc0 = (jax.lax.stop_gradient(v) for v in (c2, c1, c0))

    def newton(x):
        return x - _safe_div(_quartic(x, sc2, sc1, sc0), _quartic_slope(x, sc2, sc1))

    # Newton until every frame's step is below sqrt(eps) relative (quadratic convergence:
    # one more step reaches the rounding level), then that step.
    tol_step = float(np.sqrt(np.finfo(dtype).eps))

    def going(state):
        i, x, step = state
        return (i < _STEPS_TOP) & jnp.any(jnp.abs(step) > tol_step * jnp.abs(x))

    def step(state):
        i, x, _ = state
        x_new = newton(x)
        return i + 1, x_new, x - x_new

    start = jax.lax.stop_gradient(jnp.sqrt(-1.5 * c2))
    _, lam, _ = jax.lax.while_loop(going, step, (0, start, jnp.full_like(start, jnp.inf)))
    lam = newton(lam)
    # One more step outside stop_gradient: at the root it carries dλ = -∂P/∂N / P'(λ),
    # the exact implicit derivative.
    lam = lam - _safe_div(_quartic(lam, c2, c1, c0), _quartic_slope(lam, c2, c1))

    # λ2: largest root of the deflated cubic P(λ)/(λ - λ1), Newton from λ1 (monotone).
    l1 = jax.lax.stop_gradient(lam)
    b1, b0 = l1 * l1 + sc2, l1 * (l1 * l1 + sc2) + sc1

    def deflated_step(_, x):
        return x - _safe_div(((x + l1) * x + b1) * x + b0, (3.0 * x + 2.0 * l1) * x + b1)

    lam2 = jax.lax.fori_loop(0, _STEPS_GAP, deflated_step, l1)
    # Relative gap of N's top eigenvalue (λ1 > 0 for every pre-valid frame); an
    # unconverged λ2 lies above the root, so the gap is never overestimated.
    horn_gap = jnp.clip((l1 - lam2) / jnp.where(l1 > 0, l1, 1.0), 0.0, 1.0)
    condition = jnp.where(pre, jnp.minimum(model_ratio, horn_gap), jnp.minimum(model_ratio, 0.0))
    condition = jnp.where(ok_scale, condition, 0.0)
    valid = pre & (horn_gap > tol)

    q = _top_eigenvector(horn, lam)
    sign = jnp.where(q[0] < 0, -1.0, 1.0)  # convention w >= 0
    return [sign * qi for qi in q], valid, condition


def _safe_div(num: Array, den: Array) -> Array:
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _quartic(lam, c2, c1, c0):
    l2 = lam * lam
    return (l2 + c2) * l2 + c1 * lam + c0


def _quartic_slope(lam, c2, c1):
    return (4.0 * lam * lam + 2.0 * c2) * lam + c1


def _det3(m) -> Array:
    return (
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    )


def _minors(a):
    """2x2 minors of the top two rows (s) and the bottom two rows (c) of a 4x4."""
    s = [
        a[0][0] * a[1][1] - a[1][0] * a[0][1],
        a[0][0] * a[1][2] - a[1][0] * a[0][2],
        a[0][0] * a[1][3] - a[1][0] * a[0][3],
        a[0][1] * a[1][2] - a[1][1] * a[0][2],
        a[0][1] * a[1][3] - a[1][1] * a[0][3],
        a[0][2] * a[1][3] - a[1][2] * a[0][3],
    ]
    c = [
        a[2][0] * a[3][1] - a[3][0] * a[2][1],
        a[2][0] * a[3][2] - a[3][0] * a[2][2],
        a[2][0] * a[3][3] - a[3][0] * a[2][3],
        a[2][1] * a[3][2] - a[3][1] * a[2][2],
        a[2][1] * a[3][3] - a[3][1] * a[2][3],
        a[2][2] * a[3][3] - a[3][2] * a[2][3],
    ]
    return s, c


def _det4(a) -> Array:
    """Determinant of a 4x4 (nested lists of arrays) by Laplace expansion in 2x2 minors."""
    s, c = _minors(a)
    return s[0] * c[5] - s[1] * c[4] + s[2] * c[3] + s[3] * c[2] - s[4] * c[1] + s[5] * c[0]


def _top_eigenvector(horn, lam) -> list[Array]:
    """Unit eigenvector of symmetric N for its simple eigenvalue λ: the column of
    adj(N - λI) ∝ q qᵀ with the largest diagonal entry (∝ q_k², the best conditioned),
    chosen by masks."""
    a = [[horn[i][j] - (lam if i == j else 0.0) for j in range(4)] for i in range(4)]
    s, c = _minors(a)
    # adj[i][j] for the symmetric A; column j = row j.
    adj = [
        [
            a[1][1] * c[5] - a[1][2] * c[4] + a[1][3] * c[3],
            -a[0][1] * c[5] + a[0][2] * c[4] - a[0][3] * c[3],
            a[3][1] * s[5] - a[3][2] * s[4] + a[3][3] * s[3],
            -a[2][1] * s[5] + a[2][2] * s[4] - a[2][3] * s[3],
        ],
        [
            -a[1][0] * c[5] + a[1][2] * c[2] - a[1][3] * c[1],
            a[0][0] * c[5] - a[0][2] * c[2] + a[0][3] * c[1],
            -a[3][0] * s[5] + a[3][2] * s[2] - a[3][3] * s[1],
            a[2][0] * s[5] - a[2][2] * s[2] + a[2][3] * s[1],
        ],
        [
            a[1][0] * c[4] - a[1][1] * c[2] + a[1][3] * c[0],
            -a[0][0] * c[4] + a[0][1] * c[2] - a[0][3] * c[0],
            a[3][0] * s[4] - a[3][1] * s[2] + a[3][3] * s[0],
            -a[2][0] * s[4] + a[2][1] * s[2] - a[2][3] * s[0],
        ],
        [
            -a[1][0] * c[3] + a[1][1] * c[1] - a[1][2] * c[0],
            a[0][0] * c[3] - a[0][1] * c[1] + a[0][2] * c[0],
            -a[3][0] * s[3] + a[3][1] * s[1] - a[3][2] * s[0],
            a[2][0] * s[3] - a[2][1] * s[1] + a[2][2] * s[0],
        ],
    ]
    diag = jnp.stack([jnp.abs(adj[k][k]) for k in range(4)], axis=-1)
    pick = jax.nn.one_hot(jnp.argmax(jax.lax.stop_gradient(diag), axis=-1), 4, dtype=lam.dtype)
    col = [sum(pick[:, k] * adj[k][i] for k in range(4)) for i in range(4)]
    sq = col[0] * col[0] + col[1] * col[1] + col[2] * col[2] + col[3] * col[3]
    inv = jax.lax.rsqrt(jnp.where(sq > 0, sq, 1.0))
    return [ci * inv for ci in col]


def _second_to_first(c) -> Array:
    """Ratio e2/e1 of the two largest eigenvalues of the symmetric PSD 3x3 `c` (nested
    lists of arrays), 0 where c = 0.

    From the invariants t = e1+e2+e3, k = e1e2+e1e3+e2e3, d = e1e2e3: e1 by Newton on
    x³ - t x² + k x - d from ``|c|_F >= e1`` (monotone), then e2 and e3 as the roots of
    x² - (k - d/e1)/e1 x + d/e1. Near collinearity (e2 << e1), where the ratio decides
    validity, it is accurate to ~eps/ratio relative; for well-spread constellations an
    unconverged e1 biases it by at most a few per cent (documented in `RigidFit`).
    """
    t = c[0][0] + c[1][1] + c[2][2]
    k = (
        (c[0][0] * c[1][1] - c[0][1] * c[1][0])
        + (c[0][0] * c[2][2] - c[0][2] * c[2][0])
        + (c[1][1] * c[2][2] - c[1][2] * c[2][1])
    )
    d = _det3(c)
    x = jnp.sqrt(sum(c[a][b] * c[a][b] for a in range(3) for b in range(3)))

    def step(_, x):
        return x - _safe_div(((x - t) * x + k) * x - d, (3.0 * x - 2.0 * t) * x + k)

    x = jax.lax.fori_loop(0, _STEPS_SCATTER, step, x)
    ok = x > 0
    xs = jnp.where(ok, x, 1.0)
    prod = d / xs
    sum23 = jnp.maximum((k - prod) / xs, 0.0)
    disc = jnp.maximum(sum23 * sum23 - 4.0 * prod, 0.0)
    e2 = 0.5 * (sum23 + jnp.sqrt(disc))
    return jnp.where(ok, jnp.clip(e2 / xs, 0.0, 1.0), 0.0)


def _horn_matrix(s) -> list[list[Array]]:
    """Horn's symmetric 4x4 matrix from S[a, b] = Σ w model_a measured_b (Horn 1987, eq. 4.13)."""
    (sxx, sxy, sxz), (syx, syy, syz), (szx, szy, szz) = s
    return [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ]
