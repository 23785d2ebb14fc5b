"""Statistics of the residual of a calibration fit, as the discrepancy search uses them:
the gap (the systematic disagreement with the noise taken out) and its floor, the test
for structure against the variables the disagreement is localised by, and the binned
residual RMS against one of them. Residuals are `(N, M, 3)` [m] (frames, LEDs, axes),
NaN where there is none."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import stats

from ..recording import Recording

#: significance of residual structure against one variable, before Bonferroni
ALPHA_STRUCTURE = 0.001


def frame_variables(rec: Recording, angles: np.ndarray) -> dict[str, np.ndarray]:
    """Per-observation values `(N, M)` of the variables the disagreement is localised by."""
    from ..model import interpolate_joints

    n, m = rec.positions.shape[:2]
    out: dict[str, np.ndarray] = {"time": np.broadcast_to(rec.time[:, None], (n, m))}
    if rec.robot is not None:
        import jax.numpy as jnp

        q = np.asarray(
            interpolate_joints(
                jnp.asarray(rec.robot.time), jnp.asarray(rec.robot.joints), jnp.asarray(rec.time)
            )
        )
        for j in range(q.shape[1]):
            out[f"joint {j + 1}"] = np.broadcast_to(q[:, j, None], (n, m))
        qd = np.gradient(q, rec.time, axis=0)
        qdd = np.gradient(qd, rec.time, axis=0)
        for j in range(q.shape[1]):
            out[f"joint {j + 1} velocity"] = np.broadcast_to(qd[:, j, None], (n, m))
        out["joint speed"] = np.broadcast_to(np.linalg.norm(qd, axis=1)[:, None], (n, m))
        out["joint acceleration"] = np.broadcast_to(np.linalg.norm(qdd, axis=1)[:, None], (n, m))
    if rec.program is not None and rec.program.segment is not None:
        out["program segment"] = np.broadcast_to(rec.program.segment[:, None], (n, m))
    out["LED"] = np.broadcast_to(np.arange(m)[None, :], (n, m))
    out["emission angle"] = angles
    return out


def structure(
    residual: np.ndarray, weight: np.ndarray, variables: dict[str, np.ndarray], bins: int = 10
) -> dict[str, dict[str, Any]]:
    """χ² test per variable of binned means of the noise-normalised residual.

    Under a complete model u = r·√w is white with unit variance per axis, so the mean of
    n values in a bin has variance 1/n and ``Σ_b n_b |ū_b|²`` is χ² with 3·bins dof.
    """
    use = np.isfinite(residual[..., 0]) & (weight > 0)
    u = residual[use] * np.sqrt(weight[use])[:, None]
    out = {}
    for name, values in variables.items():
        v = np.asarray(values)[use]
        ok = np.isfinite(v)
        if ok.sum() < 20:
            continue
        uniq = np.unique(v[ok])
        if uniq.size <= bins:
            labels = np.searchsorted(uniq, v[ok])
        else:
            edges = np.unique(np.quantile(v[ok], np.linspace(0, 1, bins + 1)))
            labels = np.clip(np.searchsorted(edges, v[ok], side="right") - 1, 0, edges.size - 2)
        k = labels.max() + 1
        cnt = np.bincount(labels, minlength=k)
        sums = np.stack([np.bincount(labels, u[ok][:, a], minlength=k) for a in range(3)], 1)
        good = cnt > 0
        stat = float(np.sum(sums[good] ** 2 / cnt[good, None]))
        dof = 3 * int(good.sum())
        out[name] = {"statistic": stat, "dof": dof, "p_value": float(stats.chi2.sf(stat, dof))}
    n_tests = max(1, len(out))
    for v in out.values():
        v["significant"] = bool(v["p_value"] < ALPHA_STRUCTURE / n_tests)
    return out


def binned_rms(residual, variables, name, bins=20):
    """(bin centres, residual RMS [m]) of the 3-D residual against one variable."""
    use = np.isfinite(residual[..., 0])
    v = np.asarray(variables[name])[use]
    r2 = np.sum(residual[use] ** 2, -1)
    ok = np.isfinite(v)
    v, r2 = v[ok], r2[ok]
    edges = np.unique(np.quantile(v, np.linspace(0, 1, bins + 1)))
    lab = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, edges.size - 2)
    k = edges.size - 1
    cnt = np.bincount(lab, minlength=k)
    rms = np.sqrt(np.bincount(lab, r2, minlength=k) / np.maximum(cnt, 1))
    centre = np.bincount(lab, v, minlength=k) / np.maximum(cnt, 1)
    return centre[cnt > 0], rms[cnt > 0]


def gap(res, var3: np.ndarray, share: float = 1.0) -> float:
    """``sqrt(max(0, mean|r|² − share · mean var3))`` [m] over the observations with a
    residual; `share` = 1 − p/n, the noise fraction a fit of p parameters leaves."""
    r = res.residuals
    use = np.isfinite(r[..., 0]) & np.isfinite(var3)
    return float(np.sqrt(max(0.0, np.mean(np.sum(r[use] ** 2, -1)) - share * np.mean(var3[use]))))


def gap_floor(res, var3: np.ndarray, rel_se_var: float) -> float:
    """The gap a complete model reaches by chance [m]: two standard errors of
    ``mean|r|² − mean 3σ̂²`` (of the residual's mean square, and of the noise model's
    mean variance with relative standard error `rel_se_var`), under the root."""
    r = res.residuals
    use = np.isfinite(r[..., 0]) & np.isfinite(var3)
    r2 = np.sum(r[use] ** 2, -1)
    se_r = np.std(r2) / np.sqrt(r2.size)
    se_v = np.mean(var3[use]) * rel_se_var
    return float(np.sqrt(2.0 * np.hypot(se_r, se_v)))


def noise_share(res) -> float:
    """1 − p/n: the share of the noise variance a fit of p parameters to n residuals
    leaves in them."""
    return 1.0 - res.n_params / max(res.n_residuals, 1)


def aligned(rec: Recording, res, values: np.ndarray) -> np.ndarray:
    """`values` `(N, M)` in the recording's LED columns, reordered to `res.led_ids`."""
    col = {int(i): k for k, i in enumerate(np.asarray(rec.led_ids))}
    return values[:, [col[int(i)] for i in res.led_ids]]
