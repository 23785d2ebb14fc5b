"""Real measured data: calibrate a UR10 from laser-tracker pose measurements and find
the effects its nominal model misses, validated across measurement series.

Data: ``shared/data/ipa-robot-accuracy`` (UR10 + Leica laser tracker with a T-Mac
6-DOF probe; static poses, one measured probe pose each). See ``docs/real_ur10.md``.

Measurement model (DESIGN section 5 at pose level, through the one forward model of
`robtraj.model`)::

    camera_from_probe_i = camera_from_base(T_i) · flange_pose(q_i; effects) · flange_from_probe

with ``camera_from_base(T)`` translated by ``thermal_drift · (T − T̄)`` and positions
scaled by ``1 + tracker_scale``. The residual of pose i is 6-D: the probe-origin
position error [m] in the tracker frame and the rotation vector of
``measured⁻¹ · predicted`` [rad]. Each pose is one observation — the 4 virtual points
of the importer carry exactly this information; working with poses avoids a free
"constellation" that the bundle calibration (`robtraj.estimate.calibration.fit`)
would otherwise estimate for points that are exact by construction.

Parameters: a tangent-space correction of camera←base (6) and flange←probe (6) around
a closed-form start (Shah's robot-world/hand-eye solution), and the `Effects` fields
``joint_offset`` (6), ``link_length`` (6×2 ``[Δd, Δa]``), ``joint_compliance`` (6),
``thermal_drift`` (3) and ``tracker_scale`` (1). Identifiability: null directions of
the column-scaled Jacobian name the parameters that cannot be told apart from the
rigid transforms or from each other; those effect parameters are fixed at zero and
reported (never the rigid transforms).

Weights: per block (position, rotation) the variance is ``std_i² + s²`` where
``std_i`` is the tracker's own standard deviation of pose i (Series B; zero where the
file has none) and ``s²`` the unexplained variance of the block estimated from the
nominal fit's residuals: the residual is ~35× the tracker scatter per axis (model
error, not noise), and Series A has no std. (On Series B, pure ``1/std²`` weights
predict Series A about as well; see ``docs/real_ur10.md``.)

Cross-series prediction: effects fitted on one series are frozen and only the rigid
transforms (camera←base and flange←probe, or camera←base alone) are refitted on the
other series; its error is what the model predicts for data it never saw.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .._errors import UserError
from ..model import (
    Effects,
    camera_from_base_at,
    flange_poses,
    forward_kinematics,
    gravity_torque,
    ur10,
)

__all__ = [
    "CANDIDATES",
    "CrossSeries",
    "PoseFit",
    "PoseSeries",
    "Workflow",
    "cross_predict",
    "data_dir",
    "fit_poses",
    "load_series",
    "pose_errors",
    "run_workflow",
    "series_from_recording",
]

#: effects tried by the discrepancy workflow on pose data (geometric, then non-geometric)
#: (``joint_compliance[1,2]``: only shoulder and elbow, the joints carrying the arm's
#: weight; the wrist joints see gravity torques of a few N·m, so their compliance is
#: poorly determined and fits whatever else is left)
CANDIDATES = (
    "joint_offset",
    "link_length",
    "joint_compliance",
    "joint_compliance[1,2]",
    "thermal_drift",
)
#: the kinematic calibration of task item 1
CALIBRATION = ("joint_offset", "link_length")
#: order of the parameter vector after the 12 rigid parameters
_EFFECT_ORDER = (
    "joint_offset",
    "link_length",
    "joint_compliance",
    "thermal_drift",
    "tracker_scale",
)
_TANGENT = ("tx", "ty", "tz", "rx", "ry", "rz")
#: relative singular value below which a direction is a null direction (exact degeneracy)
_NULL_TOL = 1e-7
#: which parameter of a null direction to fix first (the UR10's known degeneracies:
#: joint-1 zero ≡ tracker yaw, d1 ≡ tracker z, joint-6 zero ≡ probe roll about the
#: flange axis, d6/a6 ≡ probe offset, d2 + d3 + d4 along parallel axes 2–4 only as a
#: sum, no gravity torque on joints 1 and 6), so that both series fix the same ones
FIX_PREFERENCE = (
    "joint_compliance[0]",
    "joint_compliance[5]",
    "joint_offset[0]",
    "link_length[0].d",
    "joint_offset[5]",
    "link_length[5].d",
    "link_length[5].a",
    "link_length[1].d",
    "link_length[2].d",
)
#: smallest relative improvement of the cross-series error that counts
MIN_CROSS_GAIN = 0.02

SERIES_FILES = {
    "A": "Series_A/measurements_grid.csv",
    "B": "Series_B/measurements_joint_configurations.csv",
}


def data_dir() -> Path:
    """``shared/data/ipa-robot-accuracy`` next to the repository (may not exist)."""
    return Path(__file__).resolve().parents[2].parent / "shared" / "data" / "ipa-robot-accuracy"


# ----------------------------------------------------------------------------- data


@dataclasses.dataclass(frozen=True)
class PoseSeries:
    """Static poses of one measurement series (SI units).

    `measured`: camera←probe `(N, 7)` jaxlie ``wxyz_xyz``; `joints` `(N, 6)` [rad];
    `temperature` `(N,)` [°C] or None; `std` `(N, 6)` tracker standard deviations
    (x, y, z [m], rx, ry, rz [rad]) or None.
    """

    name: str
    joints: np.ndarray
    measured: np.ndarray
    temperature: np.ndarray | None = None
    std: np.ndarray | None = None
    #: `(N, 6)` gravity torques [N·m] of the nominal link-mass model (computed if None)
    torque: np.ndarray | None = None

    def __post_init__(self):
        if self.torque is None:
            object.__setattr__(self, "torque", gravity_torques(self.joints))

    @property
    def start(self) -> tuple[np.ndarray, np.ndarray]:
        """Closed-form camera←base and flange←probe (computed once)."""
        if "_start" not in self.__dict__:
            object.__setattr__(self, "_start", _closed_form_start(self))
        return self.__dict__["_start"]

    @property
    def n(self) -> int:
        return int(self.joints.shape[0])

    def subset(self, idx) -> PoseSeries:
        def take(a):
            return None if a is None else np.asarray(a)[idx]

        return PoseSeries(
            self.name,
            self.joints[idx],
            self.measured[idx],
            take(self.temperature),
            take(self.std),
            take(self.torque),
        )

    def every(self, k: int) -> PoseSeries:
        return self.subset(np.arange(0, self.n, int(k)))

    def evenly(self, n: int) -> PoseSeries:
        """`n` poses evenly spaced over the series (all of them if it has fewer). Series
        thinned to the same `n` share every compiled kernel (one compilation, not one
        per series length)."""
        if n >= self.n:
            return self
        return self.subset(np.linspace(0, self.n - 1, int(n)).round().astype(int))

    @property
    def drift_variable(self) -> np.ndarray:
        """Temperature change [K] about the series mean (zeros without temperature)."""
        if self.temperature is None:
            return np.zeros(self.n)
        t = np.asarray(self.temperature, float)
        return t - t.mean()


def _wxyz_xyz_from_matrices(m: np.ndarray) -> np.ndarray:
    return np.asarray(jax.vmap(lambda a: jaxlie.SE3.from_matrix(a).wxyz_xyz)(jnp.asarray(m)))


def load_series(name: str, root: str | Path | None = None) -> PoseSeries:
    """Series ``"A"`` (grid) or ``"B"`` (joint configurations) through the pose-CSV importer."""
    from ..importers import load_pose_series

    if name not in SERIES_FILES:
        raise UserError(f"unknown series {name!r} (known: {', '.join(SERIES_FILES)})")
    path = Path(root or data_dir()) / SERIES_FILES[name]
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    joints, measured, _commanded, temperature, std = load_pose_series(path, preset="ipa-ur10")
    if joints is None:
        raise UserError(f"{path}: no joint angles")
    return PoseSeries(
        name,
        np.asarray(joints, float),
        _wxyz_xyz_from_matrices(np.asarray(measured, float)),
        None if temperature is None else np.asarray(temperature, float),
        None if std is None else np.asarray(std, float),
    )


def series_from_recording(rec, name: str = "recording") -> PoseSeries:
    """The adapter from an imported `Recording` (``robtraj import --preset ipa-ur10``):
    measured poses from `/probe/tool_pose`, joints from `/robot/joints`, temperature and
    the tracker's `/tracker/pose_std` extra."""
    if rec.probe is None or rec.robot is None:
        raise UserError("the recording has no /probe poses or no /robot joint log")
    p = rec.probe.tool_pose
    measured = np.concatenate([p.quaternion_wxyz, p.position], -1)
    std = rec.extras.get("tracker/pose_std") if rec.extras else None
    temp = None if rec.temperature is None else np.asarray(rec.temperature, float)
    return PoseSeries(name, np.asarray(rec.robot.joints, float), measured, temp, std)


# ----------------------------------------------------------------------------- parameters


def _effect_sizes(n_joints: int = 6) -> dict[str, int]:
    return {
        "joint_offset": n_joints,
        "link_length": 2 * n_joints,
        "joint_compliance": n_joints,
        "thermal_drift": 3,
        "tracker_scale": 1,
    }


def parameter_names(n_joints: int = 6) -> list[str]:
    names = [f"camera_from_base.{t}" for t in _TANGENT]
    names += [f"flange_from_probe.{t}" for t in _TANGENT]
    names += [f"joint_offset[{j}]" for j in range(n_joints)]
    names += [f"link_length[{j}].{c}" for j in range(n_joints) for c in ("d", "a")]
    names += [f"joint_compliance[{j}]" for j in range(n_joints)]
    names += [f"thermal_drift[{k}]" for k in range(3)]
    names += ["tracker_scale"]
    return names


def _slices(n_joints: int = 6) -> dict[str, slice]:
    out, k = {}, 12
    for name, size in _effect_sizes(n_joints).items():
        out[name] = slice(k, k + size)
        k += size
    return out


N_PARAMS = len(parameter_names())
_SL = _slices()


def _effects_of(theta) -> Effects:
    e = Effects.zeros(6)
    return dataclasses.replace(
        e,
        joint_offset=theta[_SL["joint_offset"]],
        link_length=theta[_SL["link_length"]].reshape(6, 2),
        joint_compliance=theta[_SL["joint_compliance"]],
        thermal_drift=theta[_SL["thermal_drift"]],
        tracker_scale=theta[_SL["tracker_scale"]][0],
    )


def _flange(eff: Effects, joints, torque) -> jaxlie.SE3:
    """base←flange: `robtraj.model.flange_poses` for static poses (no backlash), with the
    gravity torques of the nominal link-mass model precomputed (they do not depend on
    the parameters; `flange_poses` recomputes them inside every Jacobian column)."""
    robot = ur10()
    q = joints + eff.joint_offset + eff.joint_compliance * torque
    dh_delta = jnp.zeros_like(robot.dh).at[:, :2].set(eff.link_length)
    return jax.vmap(lambda qq: forward_kinematics(robot, qq, dh_delta))(q)


def gravity_torques(joints: np.ndarray) -> np.ndarray:
    """`(N, J)` gravity torques [N·m] of the nominal UR10 link-mass model."""
    robot = ur10()
    return np.asarray(jax.jit(jax.vmap(lambda q: gravity_torque(robot, q)))(jnp.asarray(joints)))


def _predict(theta, z0, x0, joints, drift, torque):
    """camera←probe predicted `(N, 7)` for the parameter vector `theta`."""
    eff = _effects_of(theta)
    z = jaxlie.SE3(z0) @ jaxlie.SE3.exp(theta[:6])
    x = jaxlie.SE3(x0) @ jaxlie.SE3.exp(theta[6:12])
    flange = _flange(eff, joints, torque)
    cam = camera_from_base_at(z, eff, drift)
    pose = cam @ flange @ x
    pos = (1.0 + eff.tracker_scale) * pose.translation()
    return jnp.concatenate([pose.rotation().wxyz, pos], -1)


def _raw_residual(theta, z0, x0, joints, drift, torque, measured):
    """`(N, 6)`: position error [m] and rotation vector [rad] of measured⁻¹·predicted."""
    pred = _predict(theta, z0, x0, joints, drift, torque)
    dp = pred[:, 4:] - measured[:, 4:]
    dr = jax.vmap(lambda a, b: (jaxlie.SO3(a).inverse() @ jaxlie.SO3(b)).log())(
        measured[:, :4], pred[:, :4]
    )
    return jnp.concatenate([dp, dr], -1)


_predict_jit = jax.jit(lambda *a: _predict(*a))


@jax.jit
def _residual_jit(theta, z0, x0, joints, drift, torque, measured):
    return _raw_residual(theta, z0, x0, joints, drift, torque, measured)


@jax.jit
def _jacobian_jit(theta, z0, x0, joints, drift, torque, measured):
    r = _raw_residual(theta, z0, x0, joints, drift, torque, measured)
    j = jax.jacfwd(_raw_residual)(theta, z0, x0, joints, drift, torque, measured)
    return r, j


# ----------------------------------------------------------------------------- errors


@jax.jit
def _relative_wxyz(a, b):
    return jax.vmap(lambda x, y: (jaxlie.SO3(x).inverse() @ jaxlie.SO3(y)).wxyz)(a, b)


def pose_errors(predicted: np.ndarray, measured: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position error [m] and single-angle orientation error [rad] per pose
    (``2·atan2(|q_xyz|, |q_w|)`` of the relative rotation, DESIGN section 6)."""
    pred, meas = np.asarray(predicted), np.asarray(measured)
    pos = np.linalg.norm(pred[:, 4:] - meas[:, 4:], axis=-1)
    rel = np.asarray(_relative_wxyz(jnp.asarray(meas[:, :4]), jnp.asarray(pred[:, :4])))
    ang = 2.0 * np.arctan2(np.linalg.norm(rel[:, 1:], axis=-1), np.abs(rel[:, 0]))
    return pos, ang


def error_summary(pos: np.ndarray, ang: np.ndarray, noise_m: float = 0.0) -> dict[str, float]:
    """mean / RMS / max position error [mm], orientation error [deg], and the gap [mm]
    (position RMS with the tracker noise taken out, DESIGN section 7)."""
    rms = float(np.sqrt(np.mean(pos**2)))
    return {
        "pos_mean_mm": float(np.mean(pos)) * 1e3,
        "pos_rms_mm": rms * 1e3,
        "pos_max_mm": float(np.max(pos)) * 1e3,
        "ang_mean_deg": float(np.rad2deg(np.mean(ang))),
        "ang_max_deg": float(np.rad2deg(np.max(ang))),
        "gap_mm": math.sqrt(max(0.0, rms**2 - 3 * noise_m**2)) * 1e3,
    }


def tracker_noise(series: PoseSeries) -> float:
    """Per-axis tracker noise σ [m] from its reported standard deviations (0 without)."""
    if series.std is None:
        return 0.0
    return float(np.sqrt(np.mean(series.std[:, :3] ** 2)))


# ----------------------------------------------------------------------------- fit


@dataclasses.dataclass(frozen=True)
class PoseFit:
    """A pose-level calibration of one series.

    `theta`: full parameter vector (`parameter_names`), zero = the start; `z0`, `x0`:
    camera←base and flange←probe at θ = 0 (``wxyz_xyz``); `free`: estimated parameters;
    `fixed_unidentifiable`: effect parameters fixed because they are not identifiable
    (with the direction they are confounded with); `sigma`: 1σ of the estimated
    parameters (`np.nan` elsewhere), from ``s²(JᵀWJ)⁻¹`` with ``s²=χ²/(n−p)``.
    """

    series: str
    estimated: tuple[str, ...]
    theta: np.ndarray
    z0: np.ndarray
    x0: np.ndarray
    free: np.ndarray
    sigma: np.ndarray
    chi2: float
    n_residuals: int
    block_sigma: tuple[float, float]
    identifiability: dict[str, Any]
    position_error: np.ndarray
    angle_error: np.ndarray
    iterations: int
    converged: bool

    @property
    def n_free(self) -> int:
        return int(self.free.sum())

    @property
    def camera_from_base(self) -> np.ndarray:
        return np.asarray((jaxlie.SE3(self.z0) @ jaxlie.SE3.exp(self.theta[:6])).wxyz_xyz)

    @property
    def flange_from_probe(self) -> np.ndarray:
        return np.asarray((jaxlie.SE3(self.x0) @ jaxlie.SE3.exp(self.theta[6:12])).wxyz_xyz)

    def effect_values(self) -> dict[str, list]:
        return {e: self.theta[_SL[parse_effect_spec(e)[0]]].tolist() for e in self.estimated}

    def parameters(self) -> dict[str, tuple[float, float]]:
        """Estimated effect parameters {name: (value, σ)} in SI units."""
        names = parameter_names()
        return {
            names[i]: (float(self.theta[i]), float(self.sigma[i]))
            for i in range(12, N_PARAMS)
            if self.free[i]
        }

    def summary(self, noise_m: float = 0.0) -> dict[str, float]:
        return error_summary(self.position_error, self.angle_error, noise_m)


def _closed_form_start(series: PoseSeries) -> tuple[np.ndarray, np.ndarray]:
    """Shah's robot-world/hand-eye solution on (at most 200) poses, nominal kinematics."""
    from ..estimate.calibration import robot_world_hand_eye

    robot = ur10()
    sel = np.linspace(0, series.n - 1, min(series.n, 200)).astype(int)
    q = jnp.asarray(series.joints[sel])
    flange = jax.jit(flange_poses)(robot, Effects.zeros(6), q, jnp.zeros_like(q)).wxyz_xyz
    z, x = robot_world_hand_eye(series.measured[sel], np.asarray(flange))
    return np.asarray(z, float), np.asarray(x, float)


def parse_effect_spec(spec: str) -> tuple[str, list[int] | None]:
    """``"joint_compliance"`` → all its parameters; ``"joint_compliance[1,2]"`` → only
    those elements (e.g. the joints that carry the arm's weight)."""
    name, _, rest = spec.partition("[")
    if name not in _SL:
        raise UserError(
            f"effect {name!r} is not fitted at pose level (choose from {_EFFECT_ORDER})"
        )
    if not rest:
        return name, None
    try:
        idx = [int(v) for v in rest.rstrip("]").split(",")]
    except ValueError:
        raise UserError(f"bad effect {spec!r}: expected NAME[i,j,...]") from None
    size = _SL[name].stop - _SL[name].start
    if any(i < 0 or i >= size for i in idx):
        raise UserError(f"bad effect {spec!r}: indices must lie in 0..{size - 1}")
    return name, idx


def _free_mask(estimate: Sequence[str], rigid: Sequence[str] = ("camera", "probe")) -> np.ndarray:
    free = np.zeros(N_PARAMS, bool)
    if "camera" in rigid:
        free[:6] = True
    if "probe" in rigid:
        free[6:12] = True
    for spec in estimate:
        name, idx = parse_effect_spec(spec)
        sl = _SL[name]
        if idx is None:
            free[sl] = True
        else:
            free[sl.start + np.asarray(idx)] = True
    return free


def identifiability(jac: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
    """Fix effect parameters along null directions of the column-scaled Jacobian.

    Repeatedly: SVD of the free, unit-norm columns; for the smallest singular direction
    below `_NULL_TOL`, fix the effect parameter (never a rigid one) with the largest
    component and record what it is confounded with. Returns the reduced mask and a
    report ``{"dropped": [{"parameter", "confounded_with"}], "condition": …}``.
    """
    names = parameter_names()
    free = free.copy()
    dropped = []
    zero = [i for i in np.flatnonzero(free) if np.linalg.norm(jac[:, i]) == 0.0]
    for i in zero:
        if i >= 12:
            free[i] = False
            dropped.append({"parameter": names[i], "confounded_with": ["(no effect on the data)"]})
    # A = Q·R: the singular values of any column subset of A are those of R's columns
    norms = np.linalg.norm(jac, axis=0)
    r_all = np.linalg.qr(jac / np.where(norms > 0, norms, 1.0), mode="r")
    while True:
        idx = np.flatnonzero(free)
        _, s, vt = np.linalg.svd(r_all[:, idx], full_matrices=False)
        rel = s / s[0]
        if rel[-1] >= _NULL_TOL:
            break
        v = vt[-1]
        cand = [(abs(v[k]), k) for k in range(idx.size) if idx[k] >= 12]
        if not cand:
            raise UserError("the rigid transforms alone are not identifiable from these poses")
        big = max(c for c, _ in cand)
        known = [
            (FIX_PREFERENCE.index(names[idx[k]]), k)
            for c, k in cand
            if c >= 0.2 * big and names[idx[k]] in FIX_PREFERENCE
        ]
        k = min(known)[1] if known else max(cand)[1]
        partners = [names[idx[m]] for m in np.argsort(-np.abs(v)) if m != k and abs(v[m]) > 0.05]
        free[idx[k]] = False
        dropped.append({"parameter": names[idx[k]], "confounded_with": partners})
    idx = np.flatnonzero(free)
    s = np.linalg.svd(r_all[:, idx], compute_uv=False)
    # order-independent explanation: each fixed parameter's column as a combination of
    # the free ones (unit-norm columns; coefficients above 0.05 are named, largest first)
    for d in dropped:
        i = names.index(d["parameter"])
        if norms[i] == 0.0:
            continue
        coef = np.linalg.lstsq(r_all[:, idx], r_all[:, i], rcond=None)[0]
        order = np.argsort(-np.abs(coef))
        d["confounded_with"] = [names[idx[m]] for m in order if abs(coef[m]) > 0.05]
    return free, {"dropped": dropped, "condition": float(s[0] / s[-1])}


def _weights(series: PoseSeries, block_sigma: tuple[float, float]) -> np.ndarray:
    """`(N, 6)` weights 1/variance (see the module docstring)."""
    sp, sr = block_sigma
    var = np.empty((series.n, 6))
    var[:, :3] = sp**2
    var[:, 3:] = sr**2
    if series.std is not None:
        std = np.nan_to_num(np.asarray(series.std, float))
        var[:, :3] += np.mean(std[:, :3] ** 2, 1, keepdims=True)
        var[:, 3:] += np.mean(std[:, 3:] ** 2, 1, keepdims=True)
    return 1.0 / var


def _block_sigma(r: np.ndarray, series: PoseSeries) -> tuple[float, float]:
    """Unexplained σ per block (position [m], rotation [rad]) beyond the tracker's std."""
    out = []
    for blk in (slice(0, 3), slice(3, 6)):
        v = float(np.mean(r[:, blk] ** 2))
        if series.std is not None:
            v -= float(np.mean(np.nan_to_num(series.std[:, blk]) ** 2))
        out.append(math.sqrt(max(v, 1e-16)))
    return out[0], out[1]


@jax.jit
def _effect_part(theta, joints, drift, torque):
    """What the effects contribute, for the rigid-only fast path: base←flange
    (``wxyz_xyz``), the thermal shift of camera←base `(N, 3)` and the scale."""
    eff = _effects_of(theta)
    flange = _flange(eff, joints, torque).wxyz_xyz
    return flange, drift[:, None] * eff.thermal_drift[None, :], eff.tracker_scale


def _rigid_residual(t12, z0, x0, flange, shift, scale, measured):
    z = jaxlie.SE3(z0) @ jaxlie.SE3.exp(t12[:6])
    x = jaxlie.SE3(x0) @ jaxlie.SE3.exp(t12[6:])
    pose = jax.vmap(lambda f: z @ jaxlie.SE3(f) @ x)(flange)
    pos = (1.0 + scale) * (pose.translation() + shift)
    dp = pos - measured[:, 4:]
    dr = jax.vmap(lambda a, b: (jaxlie.SO3(a).inverse() @ jaxlie.SO3(b)).log())(
        measured[:, :4], pose.rotation().wxyz
    )
    return jnp.concatenate([dp, dr], -1)


_rigid_residual_jit = jax.jit(_rigid_residual)


@jax.jit
def _rigid_jacobian_jit(t12, z0, x0, flange, shift, scale, measured):
    r = _rigid_residual(t12, z0, x0, flange, shift, scale, measured)
    return r, jax.jacfwd(_rigid_residual)(t12, z0, x0, flange, shift, scale, measured)


class _Problem:
    """Residual and Jacobian columns of one series; the rigid-only case (nominal model,
    cross-series refits) differentiates only the 12 rigid parameters."""

    def __init__(self, args, free):
        self.args = args
        self.idx = np.flatnonzero(free)
        self.rigid_only = bool(np.all(self.idx < 12))
        self._part = None

    def _effects(self, theta):
        if self._part is None:
            z0, x0, joints, drift, torque, _ = self.args
            self._part = _effect_part(jnp.asarray(theta), joints, drift, torque)
        return self._part

    def residual(self, theta) -> np.ndarray:
        if self.rigid_only:
            z0, x0, *_, measured = self.args
            return np.asarray(
                _rigid_residual_jit(
                    jnp.asarray(theta[:12]), z0, x0, *self._effects(theta), measured
                )
            )
        return np.asarray(_residual_jit(jnp.asarray(theta), *self.args))

    def jacobian(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """Residual `(N, 6)` and Jacobian `(6N, len(idx))` of the free columns."""
        if self.rigid_only:
            z0, x0, *_, measured = self.args
            r, j = _rigid_jacobian_jit(
                jnp.asarray(theta[:12]), z0, x0, *self._effects(theta), measured
            )
            return np.asarray(r), np.asarray(j).reshape(-1, 12)[:, self.idx]
        r, j = _jacobian_jit(jnp.asarray(theta), *self.args)
        return np.asarray(r), np.asarray(j).reshape(-1, N_PARAMS)[:, self.idx]


def _lm(theta, free, args, w, max_iter=50):
    """Levenberg–Marquardt on the weighted residuals over the `free` parameters.

    Returns ``(theta, residual (N, 6), Jacobian of the free columns, cost, iterations,
    converged)``."""
    prob = _Problem(args, free)
    sw = np.sqrt(w).reshape(-1)
    idx = prob.idx
    lam = 1e-3
    r, j = prob.jacobian(theta)
    cost = float(np.sum((r.reshape(-1) * sw) ** 2))
    it, converged = 0, False
    for it in range(1, max_iter + 1):
        a = j * sw[:, None]
        b = r.reshape(-1) * sw
        h = a.T @ a
        g = a.T @ b
        d = np.diag(h).copy()
        improved = False
        for _ in range(12):
            step = np.linalg.solve(h + lam * np.diag(np.maximum(d, 1e-30)), -g)
            trial = theta.copy()
            trial[idx] += step
            rt = prob.residual(trial)
            ct = float(np.sum((rt.reshape(-1) * sw) ** 2))
            if ct < cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            converged = True
            break
        rel = (cost - ct) / max(cost, 1e-300)
        theta, cost = trial, ct
        lam = max(lam / 10.0, 1e-12)
        r, j = prob.jacobian(theta)
        if rel < 1e-10:
            converged = True
            break
    return theta, r, j, cost, it, converged


def fit_poses(
    series: PoseSeries,
    *,
    estimate: Sequence[str] = (),
    init: PoseFit | None = None,
    fixed: PoseFit | None = None,
    rigid: Sequence[str] = ("camera", "probe"),
    block_sigma: tuple[float, float] | None = None,
    max_iter: int = 50,
) -> PoseFit:
    """Calibrate `series` at pose level (see the module docstring).

    - `estimate`: effects to fit besides the rigid transforms (`_EFFECT_ORDER`).
    - `init`: start from this fit of the same series (its θ and start transforms).
    - `fixed`: a fit of *another* series whose effects are frozen here (cross-series
      prediction); only the rigid transforms named in `rigid` are refitted.
    - `rigid`: which rigid transforms are free: ``"camera"`` (camera←base) and/or
      ``"probe"`` (flange←probe).
    - `block_sigma`: unexplained σ (position [m], rotation [rad]) used for the
      weights; default: estimated from a nominal rigid fit of this series.
    """
    if init is not None:
        theta, z0, x0 = init.theta.copy(), init.z0, init.x0
    else:
        z0, x0 = series.start
        theta = np.zeros(N_PARAMS)
    if fixed is not None:
        theta[12:] = fixed.theta[12:]
        if "probe" not in rigid:
            # same probe mounting: carry the source's flange←probe over
            x0 = fixed.flange_from_probe
            theta[6:12] = 0.0
    args = tuple(
        jnp.asarray(a)
        for a in (z0, x0, series.joints, series.drift_variable, series.torque, series.measured)
    )
    free = _free_mask(estimate, rigid)
    if block_sigma is None:
        # block weights from the residuals of a first, rigid-only pass
        t0, r0, *_ = _lm(theta.copy(), _free_mask((), rigid), args, _weights(series, (1e-3, 1e-3)))
        block_sigma = _block_sigma(r0, series)
        theta = t0
    w = _weights(series, block_sigma)
    if np.any(free[12:]):
        _, j0 = _Problem(args, np.ones(N_PARAMS, bool)).jacobian(theta)
        free, ident = identifiability(j0 * np.sqrt(w).reshape(-1)[:, None], free)
        theta = np.where(free | (np.arange(N_PARAMS) < 12), theta, 0.0)
    else:
        ident = {"dropped": [], "condition": float("nan")}
    if fixed is not None:
        theta[12:] = fixed.theta[12:]
    theta, r, j, cost, iters, conv = _lm(theta, free, args, w, max_iter)
    n_res = int(r.size)
    idx = np.flatnonzero(free)
    a = j * np.sqrt(w).reshape(-1)[:, None]
    s2 = cost / max(1, n_res - idx.size)
    sigma = np.full(N_PARAMS, np.nan)
    sigma[idx] = np.sqrt(np.diag(np.linalg.pinv(a.T @ a)) * s2)
    pred = np.asarray(_predict_jit(jnp.asarray(theta), *args[:5]))
    pos, ang = pose_errors(pred, series.measured)
    return PoseFit(
        series=series.name,
        estimated=tuple(estimate) if fixed is None else fixed.estimated,
        theta=theta,
        z0=np.asarray(z0),
        x0=np.asarray(x0),
        free=free,
        sigma=sigma,
        chi2=cost,
        n_residuals=n_res,
        block_sigma=tuple(float(b) for b in block_sigma),
        identifiability=ident,
        position_error=pos,
        angle_error=ang,
        iterations=iters,
        converged=conv,
    )


def cross_predict(
    source: PoseFit, target: PoseSeries, rigid: Sequence[str] = ("camera", "probe")
) -> PoseFit:
    """Predict `target` with `source`'s effects frozen; refit only the `rigid` transforms."""
    return fit_poses(target, fixed=source, rigid=rigid)


# ----------------------------------------------------------------------------- workflow


@dataclasses.dataclass(frozen=True)
class CrossSeries:
    """One model (set of effects) fitted on each series and predicting the other."""

    effects: tuple[str, ...]
    fitted: dict[str, PoseFit]
    cross: dict[str, PoseFit]  # key "A->B": fitted on A, predicting B

    def row(self, noise: dict[str, float]) -> dict[str, dict[str, float]]:
        out = {f"fit {k}": v.summary(noise[k]) for k, v in self.fitted.items()}
        out.update({k: v.summary(noise[k[-1]]) for k, v in self.cross.items()})
        return out


def evaluate(
    effects: Sequence[str],
    series: dict[str, PoseSeries],
    rigid: Sequence[str] = ("camera", "probe"),
    block_sigma: dict[str, tuple[float, float]] | None = None,
) -> CrossSeries:
    """Fit `effects` on every series and predict each other series from it."""
    fitted = {
        k: fit_poses(
            s, estimate=effects, block_sigma=None if block_sigma is None else block_sigma[k]
        )
        for k, s in series.items()
    }
    cross = {}
    for a in series:
        for b in series:
            if a != b:
                cross[f"{a}->{b}"] = fit_poses(
                    series[b],
                    fixed=fitted[a],
                    rigid=rigid,
                    block_sigma=None if block_sigma is None else block_sigma[b],
                )
    return CrossSeries(tuple(effects), fitted, cross)


def _bic(before: PoseFit, after: PoseFit) -> dict[str, Any]:
    """Likelihood ratio with the noise scale profiled out (σ² estimated from the data)
    and ΔBIC = LR − Δk·ln n (positive: the effect is supported)."""
    from scipy import stats

    n = after.n_residuals
    k = after.n_free - before.n_free
    lr = n * math.log(max(before.chi2, 1e-300) / max(after.chi2, 1e-300))
    return {
        "likelihood_ratio": lr,
        "dof": k,
        "p_value": float(stats.chi2.sf(max(lr, 0.0), max(k, 1))),
        "delta_bic": lr - k * math.log(n),
    }


def _cross_cost(cs: CrossSeries) -> dict[str, tuple[float, float]]:
    """Cross-series error per direction: position RMS [m] and angle RMS [rad]."""
    return {
        k: (
            float(np.sqrt(np.mean(v.position_error**2))),
            float(np.sqrt(np.mean(v.angle_error**2))),
        )
        for k, v in cs.cross.items()
    }


@dataclasses.dataclass(frozen=True)
class Workflow:
    """The discrepancy workflow on pose data, validated across series.

    `steps`: one dict per named effect (``effect``, ``fitted`` and ``cross`` summaries,
    per-series ``score`` and ``parameters``); `rejected`: candidates that improved
    the fitted series (ΔBIC > 0) but not the cross-series prediction (over-fitting),
    with the round they were tried in; `models`: the CrossSeries after each step
    (index 0: nominal rigid); `calibration`: the kinematic calibration of item 1.
    """

    series: tuple[str, ...]
    rigid: tuple[str, ...]
    noise_m: dict[str, float]
    models: list[CrossSeries]
    steps: list[dict[str, Any]]
    rejected: list[dict[str, Any]]
    candidates_tried: list[dict[str, Any]]
    calibration: CrossSeries

    @property
    def named(self) -> list[str]:
        return [s["effect"] for s in self.steps]

    def table(self) -> list[dict[str, Any]]:
        """Rows (model, column, figures) for the report table."""
        rows = []
        labels = ["nominal rigid"] + [f"+ {e}" for e in self.named]
        for label, m in zip(labels, self.models):
            for col, vals in m.row(self.noise_m).items():
                rows.append({"model": label, "column": col, **vals})
        for col, vals in self.calibration.row(self.noise_m).items():
            rows.append(
                {
                    "model": "calibration (" + " + ".join(self.calibration.effects) + ")",
                    "column": col,
                    **vals,
                }
            )
        return rows

    def markdown(self) -> str:
        """The report table: mean / max position [mm], orientation [deg], gap [mm]."""
        return rows_markdown(self.table())


def _relative_gain(before: dict, after: dict, which: int | None = None) -> dict[str, float]:
    """Relative decrease of the cross-series error per direction: of the position RMS
    (`which=0`), the angle RMS (`which=1`) or, by default, the mean of the two."""
    out = {}
    for k in before:
        g = [(before[k][i] - after[k][i]) / before[k][i] for i in (0, 1)]
        out[k] = float(0.5 * (g[0] + g[1]) if which is None else g[which])
    return out


def run_workflow(
    series: dict[str, PoseSeries],
    *,
    candidates: Sequence[str] = CANDIDATES,
    rigid: Sequence[str] = ("camera", "probe"),
    max_steps: int = 4,
    min_cross_gain: float = MIN_CROSS_GAIN,
    progress: Callable[[str], None] | None = None,
) -> Workflow:
    """Greedy discrepancy workflow with cross-series validation.

    Start: the nominal rigid model (only camera←base and flange←probe fitted). Each
    round fits every remaining candidate added to the named ones on every series and
    scores it (a) on the fitted series by a likelihood ratio with σ profiled and ΔBIC,
    and (b) by the cross-series prediction: effects frozen, the `rigid` transforms
    refitted on the other series. A candidate is eligible only if ΔBIC > 0 on every
    fitted series **and** the cross-series cost (mean relative decrease of position
    and orientation RMS) falls by at least `min_cross_gain` in every direction; the
    eligible one with the largest summed ΔBIC is named. A candidate with ΔBIC > 0 that
    fails (b) is recorded in `rejected` as over-fitting. Stops when none is eligible.
    """
    say = progress or (lambda _m: None)
    noise = {k: tracker_noise(s) for k, s in series.items()}
    nz = [v for v in noise.values() if v > 0]
    if nz:  # same tracker: a series without reported std gets the others' noise level
        noise = {k: (v if v > 0 else float(np.mean(nz))) for k, v in noise.items()}
    say("nominal rigid fit")
    current = evaluate((), series, rigid)
    bsig = {k: v.block_sigma for k, v in current.fitted.items()}
    models = [current]
    named: list[str] = []
    steps: list[dict[str, Any]] = []
    rejected: list[dict[str, Any]] = []
    tried: list[dict[str, Any]] = []
    for rnd in range(max_steps):
        taken = {parse_effect_spec(c)[0] for c in named}
        remaining = [c for c in candidates if parse_effect_spec(c)[0] not in taken]
        if not remaining:
            break
        base_cross = _cross_cost(current)
        scored = {}
        for cand in remaining:
            say(f"round {rnd + 1}: trying {cand}")
            cs = evaluate((*named, cand), series, rigid, bsig)
            score = {k: _bic(current.fitted[k], cs.fitted[k]) for k in series}
            gain = _relative_gain(base_cross, _cross_cost(cs))
            fits_better = all(s["delta_bic"] > 0 for s in score.values())
            predicts_better = all(g >= min_cross_gain for g in gain.values())
            entry = {
                "round": rnd + 1,
                "effect": cand,
                "score": score,
                "cross_gain": gain,
                "cross_gain_position": _relative_gain(base_cross, _cross_cost(cs), which=0),
                "cross_gain_angle": _relative_gain(base_cross, _cross_cost(cs), which=1),
                "fits_better": fits_better,
                "predicts_better": predicts_better,
            }
            tried.append(entry)
            scored[cand] = (cs, entry)
        eligible = {
            c: v for c, v in scored.items() if v[1]["fits_better"] and v[1]["predicts_better"]
        }
        for c, (_, entry) in scored.items():
            if entry["fits_better"] and not entry["predicts_better"] and c not in eligible:
                rejected.append(entry)
        if not eligible:
            break
        best = max(
            eligible, key=lambda c: sum(s["delta_bic"] for s in eligible[c][1]["score"].values())
        )
        current, entry = eligible[best]
        named.append(best)
        models.append(current)
        steps.append(
            {
                **entry,
                "parameters": {k: f.parameters() for k, f in current.fitted.items()},
                "fixed_unidentifiable": {
                    k: [d["parameter"] for d in f.identifiability["dropped"]]
                    for k, f in current.fitted.items()
                },
                "summary": current.row(noise),
            }
        )
        say(f"named {best}")
    say("kinematic calibration")
    calib = evaluate(CALIBRATION, series, rigid, bsig)
    return Workflow(
        series=tuple(series),
        rigid=tuple(rigid),
        noise_m=noise,
        models=models,
        steps=steps,
        rejected=rejected,
        candidates_tried=tried,
        calibration=calib,
    )


# ----------------------------------------------------------------------------- helpers


def transform_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Translation [m] and single rotation angle [rad] between two ``wxyz_xyz`` poses."""
    pos, ang = pose_errors(np.asarray(a)[None], np.asarray(b)[None])
    return float(pos[0]), float(ang[0])


def rigid_variants(model: CrossSeries, series: dict[str, PoseSeries]) -> dict[str, dict]:
    """Cross-series prediction with only camera←base refitted (flange←probe carried over
    from the fitting series) next to the default (camera←base and flange←probe refitted):
    ``{direction: {"camera": PoseFit, "camera+probe": PoseFit}}``."""
    out = {}
    for key, fit in model.cross.items():
        src, dst = key.split("->")
        only = fit_poses(
            series[dst],
            fixed=model.fitted[src],
            rigid=("camera",),
            block_sigma=fit.block_sigma,
        )
        out[key] = {"camera": only, "camera+probe": fit}
    return out


def rows_markdown(rows: list[dict[str, Any]]) -> str:
    """A markdown table of `Workflow.table()`-style rows."""
    head = (
        "| model | evaluated on | pos mean [mm] | pos max [mm] | ang mean [deg] "
        "| ang max [deg] | gap [mm] |\n|---|---|---|---|---|---|---|\n"
    )
    return head + "".join(
        f"| {r['model']} | {r['column']} | {r['pos_mean_mm']:.3f} | {r['pos_max_mm']:.3f} "
        f"| {r['ang_mean_deg']:.4f} | {r['ang_max_deg']:.4f} | {r['gap_mm']:.3f} |\n"
        for r in rows
    )
