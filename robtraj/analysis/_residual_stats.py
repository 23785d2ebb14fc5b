"""Statistics of the residual of a calibration fit, as the discrepancy search uses them:
the gap (the systematic disagreement with the noise taken out) and its floor, the test
for structure against the variables the disagreement is localised by, and the binned
residual RMS against one of them. Residuals are `(N, M, 3)` [m] (frames, LEDs, axes),
NaN where there is none."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from scipy import stats

from ..recording import Recording

#: significance of residual structure against one variable, before Bonferroni
ALPHA_STRUCTURE = 0.001


def frame_variables(
    rec: Recording, angles: np.ndarray, *, derived: bool = False
) -> dict[str, np.ndarray]:
    """Per-observation values `(N, M)` (the recording's LED columns) of the variables the
    disagreement is localised by: time, each joint's angle and velocity, the joint speed
    and acceleration, the program segment, the LED and its emission angle.

    `derived`: also the camera's `temperature` [°C] (where the recording has one that
    varies), the `LED distance` from the camera [m] (|measured position|) and each
    joint's gravity torque (``joint j torque`` [N·m], `robtraj.model.gravity_torque`).
    The localisation ranks them too (`robtraj.analysis.discrepancy`); the structure test
    that steers the search (`structure`) is left to the variables above, so that the
    search decides as it was validated to."""
    n, m = rec.positions.shape[:2]

    def each(values: np.ndarray) -> np.ndarray:
        return np.broadcast_to(np.asarray(values)[:, None], (n, m))

    out: dict[str, np.ndarray] = {"time": each(rec.time)}
    if derived and rec.temperature is not None:
        temperature = np.asarray(rec.temperature, float)
        if np.unique(temperature[np.isfinite(temperature)]).size > 1:
            out["temperature"] = each(temperature)
    q = None
    if rec.robot is not None:
        q = _joint_angles(rec)
        for j in range(q.shape[1]):
            out[f"joint {j + 1}"] = each(q[:, j])
        qd = np.gradient(q, rec.time, axis=0)
        qdd = np.gradient(qd, rec.time, axis=0)
        for j in range(q.shape[1]):
            out[f"joint {j + 1} velocity"] = each(qd[:, j])
        out["joint speed"] = each(np.linalg.norm(qd, axis=1))
        out["joint acceleration"] = each(np.linalg.norm(qdd, axis=1))
    if rec.program is not None and rec.program.segment is not None:
        out["program segment"] = each(rec.program.segment)
    out["LED"] = np.broadcast_to(np.arange(m)[None, :], (n, m))
    out["emission angle"] = angles
    if derived:
        out["LED distance"] = np.sqrt(np.sum(np.asarray(rec.positions) ** 2, -1))
        if q is not None:
            torque = _gravity_torques(rec, q)
            for j in range(0 if torque is None else torque.shape[1]):
                out[f"joint {j + 1} torque"] = each(torque[:, j])
    return out


def _joint_angles(rec: Recording) -> np.ndarray:
    """The logged joint angles `(N, joints)` [rad] at the tracker's frames."""
    import jax.numpy as jnp

    from ..model import interpolate_joints

    return np.asarray(
        interpolate_joints(
            jnp.asarray(rec.robot.time), jnp.asarray(rec.robot.joints), jnp.asarray(rec.time)
        )
    )


def _gravity_torques(rec: Recording, q: np.ndarray) -> np.ndarray | None:
    """Each joint's gravity torque `(N, joints)` [N·m] at joint angles `q` from the
    recording's robot model; None when the log names no model."""
    import jax.numpy as jnp

    from .._errors import UserError
    from ..model import robot_from_log

    try:
        robot = robot_from_log(rec.robot)
    except UserError:
        return None
    return np.asarray(_per_frame_torque()(robot, jnp.asarray(q)))


@functools.cache
def _per_frame_torque():
    """`robtraj.model.gravity_torque` over frames `(N, joints)`, compiled once per shape."""
    import equinox as eqx
    import jax

    from ..model import gravity_torque

    return eqx.filter_jit(jax.vmap(gravity_torque, in_axes=(None, 0)))


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
