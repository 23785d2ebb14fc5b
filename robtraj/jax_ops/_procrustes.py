"""Weighted rigid fit (no scale) of a constellation to measured points: Horn's method."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int


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
    - `condition`: `(frames,)` in [0, 1]: the smaller of (a) the ratio of the second to
      the largest eigenvalue of the weighted model scatter and (b) the relative gap of
      the two largest eigenvalues of Horn's matrix. Near 0 means (nearly) collinear
      LEDs, where the rotation about the line is undetermined.
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


@jax.custom_jvp
def _top_eigh(n: Array) -> tuple[Array, Array, Array]:
    """Largest eigenvalue, its eigenvector and all eigenvalues of symmetric (..., 4, 4)."""
    w, v = jnp.linalg.eigh(n)
    return w[..., -1], v[..., :, -1], w


@_top_eigh.defjvp
def _top_eigh_jvp(primals, tangents):
    # Only the gaps to the top eigenvalue enter (first-order perturbation theory); JAX's
    # eigh JVP uses all pairs and gives NaN when two *other* eigenvalues coincide, which
    # happens for symmetric constellations.
    (n,), (dn,) = primals, tangents
    w, v = jnp.linalg.eigh(n)
    top, vec = w[..., -1], v[..., :, -1]
    dn = 0.5 * (dn + jnp.swapaxes(dn, -1, -2))
    gap = top[..., None] - w  # (..., 4), 0 for the top itself
    ok = gap > 0
    inv = jnp.where(ok, 1.0 / jnp.where(ok, gap, 1.0), 0.0)
    inv = inv.at[..., -1].set(0.0)
    dn_vec = jnp.einsum("...ij,...j->...i", dn, vec)
    coeff = jnp.einsum("...ji,...j->...i", v, dn_vec)  # v_i · dN · vec
    dtop = coeff[..., -1]
    dvec = jnp.einsum("...ij,...j->...i", v, inv * coeff)
    dw = jnp.einsum("...ji,...jk,...ki->...i", v, dn, v)
    return (top, vec, w), (dtop, dvec, dw)


def _horn_matrix(s: Array) -> Array:
    """Horn's symmetric 4x4 matrix from S[a, b] = Σ w model_a measured_b (Horn 1987, eq. 4.13)."""
    sxx, sxy, sxz = s[..., 0, 0], s[..., 0, 1], s[..., 0, 2]
    syx, syy, syz = s[..., 1, 0], s[..., 1, 1], s[..., 1, 2]
    szx, szy, szz = s[..., 2, 0], s[..., 2, 1], s[..., 2, 2]
    rows = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def weighted_procrustes(
    model: Float[Array, "leds 3"] | Float[Array, "frames leds 3"],
    measured: Float[Array, "frames leds 3"],
    weights: Float[Array, "frames leds"],
) -> RigidFit:
    """Weighted least-squares rigid transform per frame: ``measured ≈ R · model + t``.

    Minimises ``Σ_k w_k |R p_k + t - y_k|²`` over proper rotations R (det +1, never a
    reflection) and translations t, in closed form with Horn's unit-quaternion method:
    the rotation is the eigenvector of the largest eigenvalue of a symmetric 4x4 matrix
    built from the weighted centred cross-covariance. Exact least-squares solution, so it
    also eliminates per-frame poses in a bundle adjustment. Differentiable w.r.t.
    `model`, `measured` and `weights` (the eigenvector gradient uses only the gap to the
    top eigenvalue, which is non-zero for every valid frame).

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
    """
    if measured.ndim != 3 or measured.shape[-1] != 3:
        raise ValueError(f"measured must be (frames, leds, 3), got {measured.shape}")
    if model.shape[-2:] != measured.shape[-2:] or model.ndim not in (2, 3):
        raise ValueError(f"model {model.shape} does not match measured {measured.shape}")
    if weights.shape != measured.shape[:2]:
        raise ValueError(f"weights {weights.shape} do not match measured {measured.shape}")
    dtype = jnp.result_type(model, measured, weights)
    model = jnp.broadcast_to(model.astype(dtype), measured.shape)
    return _weighted_procrustes(model, measured.astype(dtype), weights.astype(dtype))


@jax.jit
def _weighted_procrustes(model: Array, measured: Array, weights: Array) -> RigidFit:
    return RigidFit(*jax.vmap(_fit_frame)(model, measured, weights))


def _fit_frame(model: Array, measured: Array, weights: Array) -> tuple[Array, ...]:
    """One frame: model (M, 3), measured (M, 3), weights (M,)."""
    dtype = measured.dtype
    tol = collinear_threshold(dtype)
    used = (
        (weights > 0)
        & jnp.isfinite(weights)
        & jnp.all(jnp.isfinite(measured), axis=-1)
        & jnp.all(jnp.isfinite(model), axis=-1)
    )
    # double-where: make masked entries safe before any arithmetic.
    w = jnp.where(used, weights, 0.0)
    p = jnp.where(used[:, None], model, 0.0)
    y = jnp.where(used[:, None], measured, 0.0)
    n_used = jnp.sum(used)
    wsum = jnp.sum(w)
    wsum_safe = jnp.where(wsum > 0, wsum, 1.0)
    wn = w / wsum_safe
    p_bar = wn @ p
    y_bar = wn @ y
    pc = jnp.where(used[:, None], p - p_bar, 0.0)
    yc = jnp.where(used[:, None], y - y_bar, 0.0)

    # Weighted model scatter: collinearity check relative to its size.
    scatter = jnp.einsum("k,ki,kj->ij", wn, pc, pc)
    e = jnp.linalg.eigvalsh(scatter)
    e1 = e[2]
    model_ratio = jnp.where(e1 > 0, e[1] / jnp.where(e1 > 0, e1, 1.0), 0.0)

    s = jnp.einsum("k,ki,kj->ij", wn, pc, yc)  # S[a, b] = Σ w model_a measured_b
    # Scale to O(1) (eigenvectors are scale-invariant): helps float32 with small inputs.
    scale = jnp.sqrt(jnp.trace(scatter) * jnp.sum(wn * jnp.sum(yc * yc, axis=-1)))
    ok_scale = scale > jnp.finfo(dtype).tiny
    horn = _horn_matrix(s / jnp.where(ok_scale, scale, 1.0))
    pre = (n_used >= 3) & ok_scale & (model_ratio > tol)
    # Benign matrix for frames that are invalid already (keeps eigh and its JVP finite).
    benign = jnp.diag(jnp.array([1.0, 0.0, -1.0, -2.0], dtype))
    horn = jnp.where(pre, horn, benign)
    top, q, evals = _top_eigh(horn)
    spread = jnp.maximum(top - evals[0], jnp.finfo(dtype).tiny)
    horn_gap = (top - evals[2]) / spread
    condition = jnp.minimum(model_ratio, horn_gap)
    valid = pre & (horn_gap > tol)

    q = q / jnp.linalg.norm(q)
    q = jnp.where(q[0] < 0, -q, q)  # convention w >= 0
    r = _quat_to_matrix(q)
    t = y_bar - r @ p_bar
    res = y - (p @ r.T + t)
    ms = jnp.sum(w * jnp.sum(res * res, axis=-1)) / wsum_safe
    # double-where: sqrt has an infinite derivative at a perfect fit.
    rms = jnp.where(ms > 0, jnp.sqrt(jnp.where(ms > 0, ms, 1.0)), 0.0)
    nan = jnp.array(jnp.nan, dtype)
    # Field order of RigidFit.
    return (
        jnp.where(valid, q, nan),
        jnp.where(valid, t, nan),
        jnp.where(valid, rms, nan),
        n_used,
        valid,
        condition,
    )


def _quat_to_matrix(q: Array) -> Array:
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
        ]
    )
