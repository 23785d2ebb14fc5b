"""Closed-form initialisation of the bundle calibration (DESIGN section 5.4).

1. Robot poses: static dwells from the joint log (all joints slower than a threshold
   for at least `min_dwell` seconds); each dwell gives one mean joint vector and the
   mean position of each LED seen in it. When the dwells make fewer than six distinct
   poses, up to `max_moving` single moving frames (evenly spread) are added.
2. Tool poses in the camera frame: weighted Procrustes of the reference constellation
   to each group's LED positions (`robtraj.jax_ops.weighted_procrustes`).
3. Flange poses: forward kinematics of the group's joints (nominal robot + fixed effects).
4. Robot-world/hand-eye ``camera_from_tool_i = Z · base_from_flange_i · X`` solved by
   Shah's closed form (Kronecker null space of the rotation equations, then
   orthonormalisation, then linear least squares for the translations); for a run whose
   flange does not rotate about two axes, a point registration of the tool origins with
   the nominal flange←tool translation instead (`closed_form_start`).

A fit starts there (`start_poses`), or at a previous calibration's values, with the
effects at that calibration's values or zero (`start_effects`).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from .._errors import UserError
from ..model import EFFECT_NAMES, Effects, flange_poses
from ..recording import Pose
from ._calib_data import CalibrationData
from ._calib_parameters import dictionary_terms

_STATIC_SPEED = 1e-4  # [rad/s] every joint slower than this: the robot stands still
_DISTINCT = 1e-3  # [rad] joint vectors closer than this are the same pose
_ENOUGH_DWELLS = 6  # fewer distinct dwells: add single moving frames as poses


def dwells(data: CalibrationData, min_dwell: float) -> list[np.ndarray]:
    """Frame-index arrays (into `data`) of static dwells."""
    speed = np.abs(np.gradient(data.joints, data.log_time, axis=0)).max(1)
    k = np.clip(np.searchsorted(data.log_time, data.time, side="right") - 1, 0, None)
    k1 = np.clip(k + 1, 0, data.log_time.shape[0] - 1)
    static = (speed[k] < _STATIC_SPEED) & (speed[k1] < _STATIC_SPEED)
    gaps = np.diff(data.time) > 5 * np.median(np.diff(data.time)) if data.n_frames > 1 else []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], static.astype(np.int8), [0]])))
    out = []
    for a, b in zip(edges[::2], edges[1::2]):
        if data.time[b - 1] - data.time[a] < min_dwell or b - a < 3:
            continue
        cut = np.flatnonzero(gaps[a : b - 1]) + a + 1 if len(gaps) else []
        for part in np.split(np.arange(a, b), cut):
            if part.size >= 3:
                out.append(part)
    return out


def _distinct(q: np.ndarray) -> int:
    """Number of joint vectors in `q` `(G, joints)` farther than `_DISTINCT` from every
    earlier one kept (greedy)."""
    reps = q[:0]
    for row in q:
        if not reps.shape[0] or np.min(np.max(np.abs(reps - row), axis=1)) > _DISTINCT:
            reps = np.concatenate([reps, row[None]])
    return reps.shape[0]


def _rotation_rank(quats: np.ndarray) -> int:
    """Number of independent rotation axes among the poses' rotations relative to the first."""
    r = Rotation.from_quat(quats, scalar_first=True)
    rv = (r[0].inv() * r).as_rotvec()
    s = np.linalg.svd(rv, compute_uv=False) if rv.shape[0] > 1 else np.zeros(1)
    return int(np.sum(s > np.deg2rad(1.0)))


# The closed form is NumPy on a few hundred poses: its conversions go through SciPy's
# rotations (jaxlie's, called eagerly, would compile each of their operations).
def _matrices(poses: np.ndarray) -> np.ndarray:
    """`(G, 4, 4)` homogeneous matrices of poses `(G, 7)` wxyz_xyz."""
    m = np.zeros((poses.shape[0], 4, 4))
    m[:, :3, :3] = Rotation.from_quat(poses[:, :4], scalar_first=True).as_matrix()
    m[:, :3, 3] = poses[:, 4:]
    m[:, 3, 3] = 1.0
    return m


def _pose_from_matrix(m: np.ndarray) -> np.ndarray:
    """wxyz_xyz `(7,)` of a homogeneous matrix `(4, 4)` (w ≥ 0)."""
    q = Rotation.from_matrix(m[:3, :3]).as_quat(canonical=True, scalar_first=True)
    return np.concatenate([q, m[:3, 3]])


@jax.jit
def _procrustes(model, measured, weight):
    from ..jax_ops import weighted_procrustes

    return weighted_procrustes(model, jnp.where(weight[..., None] > 0, measured, jnp.nan), weight)


@jax.jit
def _flange(robot, effects, q):
    return flange_poses(robot, effects, q, jnp.ones_like(q)).wxyz_xyz


def pose_pairs(
    data: CalibrationData,
    effects: Effects,
    constellation: np.ndarray,
    *,
    min_dwell: float = 0.2,
    max_moving: int = 60,
) -> tuple[np.ndarray, np.ndarray, int]:
    """``(camera_from_tool (G, 7), base_from_flange (G, 7), n_dwells)`` as jaxlie
    ``wxyz_xyz`` for the groups (static dwells first, then moving frames if needed)."""
    groups_static = dwells(data, min_dwell)
    moving = np.ones(data.n_frames, bool)
    for d in groups_static:
        moving[d] = False
    groups = list(groups_static)
    q_all = data.joints_at(np.arange(data.n_frames))
    q_groups = [q_all[d].mean(0) for d in groups]
    if not groups or _distinct(np.array(q_groups)) < _ENOUGH_DWELLS:
        idx = np.flatnonzero(moving & (data.seen.sum(1) >= 4))
        if idx.size:
            take = idx[np.linspace(0, idx.size - 1, min(max_moving, idx.size)).round().astype(int)]
            groups += [np.array([i]) for i in np.unique(take)]
            q_groups += [q_all[i] for i in np.unique(take)]
    n_distinct = _distinct(np.array(q_groups)) if q_groups else 0
    if n_distinct <= 1:
        raise UserError(
            "all usable frames are at one robot pose: calibration needs the robot at several "
            "distinct poses (at least 3, rotated about different axes)"
        )
    if n_distinct < 3:
        raise UserError(
            f"only {n_distinct} distinct robot poses in the recording; calibration needs at "
            "least 3, rotated about different axes"
        )
    mean = np.full((len(groups), data.n_leds, 3), np.nan)
    weight = np.zeros((len(groups), data.n_leds))
    for i, g in enumerate(groups):
        seen = data.seen[g]
        cnt = seen.sum(0)
        ok = cnt >= max(1, 0.5 * g.size)
        s = data.measured_sum(g)
        mean[i, ok] = s[ok] / cnt[ok, None]
        weight[i, ok] = cnt[ok]
    n_groups = len(groups)
    pad = -n_groups % 32  # fixed shapes: one compilation for many recordings
    mean = np.concatenate([mean, np.zeros((pad, *mean.shape[1:]))])
    weight = np.concatenate([weight, np.zeros((pad, weight.shape[1]))])
    fit = _procrustes(np.asarray(constellation, float), mean, weight)
    valid = (np.asarray(fit.valid) & ((weight > 0).sum(1) >= 3))[:n_groups]
    camera_from_tool = np.concatenate(
        [np.asarray(fit.quaternion_wxyz), np.asarray(fit.position)], -1
    )[:n_groups]
    q = np.array(q_groups)
    q_pad = np.concatenate([q, np.repeat(q[:1], pad, 0)])
    base_from_flange = np.asarray(_flange(data.robot, effects, q_pad))[:n_groups]
    camera_from_tool, base_from_flange = camera_from_tool[valid], base_from_flange[valid]
    if _distinct(q[valid]) < 3:
        raise UserError(
            "too few distinct robot poses with the tool seen: calibration needs at least 3 "
            "poses, rotated about two different axes to determine every parameter"
        )
    return camera_from_tool, base_from_flange, len(groups_static)


def closed_form_start(
    camera_from_tool: np.ndarray, base_from_flange: np.ndarray, flange_from_tool: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(camera_from_base, flange_from_tool)`` (``wxyz_xyz``) to start the refinement
    from: Shah's closed form (`robot_world_hand_eye`) when the flange rotates about two
    different axes; otherwise (a run that keeps the tool's orientation, or turns it about
    one axis) the camera←base that best maps the flange's tool origins onto the measured
    tool positions with the nominal `flange_from_tool` translation (Kabsch), and the mean
    flange←tool rotation that fits then. Such a run cannot determine every parameter; the
    refinement names what it leaves undetermined."""
    if _rotation_rank(base_from_flange[:, :4]) >= 2:
        return robot_world_hand_eye(camera_from_tool, base_from_flange)
    A, B = _matrices(camera_from_tool), _matrices(base_from_flange)
    t_x = np.asarray(flange_from_tool)[4:]
    src = np.einsum("gij,j->gi", B[:, :3, :3], t_x) + B[:, :3, 3]  # tool origins, base frame
    dst = A[:, :3, 3]  # tool origins, camera frame
    sc, dc = src - src.mean(0), dst - dst.mean(0)
    if np.linalg.svd(sc, compute_uv=False)[1] < 1e-3 * max(np.abs(sc).max(), 1e-12):
        raise UserError(
            "the tool is neither rotated about two axes nor moved off a line: camera←base "
            "cannot be determined from this recording"
        )
    u, _, vt = np.linalg.svd(dc.T @ sc)
    rz = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    tz = dst.mean(0) - rz @ src.mean(0)
    # R_A = R_Z R_B R_X for every pose: the chordal mean of R_B⁻¹ R_Z⁻¹ R_A
    rx = _orthonormal(np.einsum("gji,kj,gkl->il", B[:, :3, :3], rz, A[:, :3, :3]))
    Z = np.eye(4)
    Z[:3, :3], Z[:3, 3] = rz, tz
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = rx, t_x
    return (
        _pose_from_matrix(Z),
        _pose_from_matrix(X),
    )


def _orthonormal(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    r = u @ vt
    if np.linalg.det(r) < 0:
        r = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return r


def robot_world_hand_eye(
    camera_from_tool: np.ndarray, base_from_flange: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form ``(camera_from_base, flange_from_tool)`` (jaxlie ``wxyz_xyz``, `(7,)`).

    Solves ``camera_from_tool_i = Z · base_from_flange_i · X`` for Z = camera←base and
    X = flange←tool by Shah's method (2013): with Y = X⁻¹ the rotations satisfy
    ``R_A R_Y = R_Z R_B``, a linear system in vec(R_Y), vec(R_Z) whose null vector is
    scaled and orthonormalised; then ``R_A t_Y − t_Z = R_Z t_B − t_A`` by least squares.
    Inputs `(G, 7)` ``wxyz_xyz``, G ≥ 3 poses rotated about two different axes.
    """
    A, B = _matrices(camera_from_tool), _matrices(base_from_flange)
    eye = np.eye(3)
    rows = [np.hstack([np.kron(eye, a[:3, :3]), -np.kron(b[:3, :3].T, eye)]) for a, b in zip(A, B)]
    _, _, vt = np.linalg.svd(np.vstack(rows))
    v = vt[-1]
    ry = v[:9].reshape(3, 3, order="F")
    rz = v[9:].reshape(3, 3, order="F")
    d = np.linalg.det(ry)
    alpha = np.sign(d) * np.abs(d) ** (-1.0 / 3.0)
    ry, rz = _orthonormal(alpha * ry), _orthonormal(alpha * rz)
    lhs = np.vstack([np.hstack([a[:3, :3], -eye]) for a in A])
    rhs = np.concatenate([rz @ b[:3, 3] - a[:3, 3] for a, b in zip(A, B)])
    sol = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    ty, tz = sol[:3], sol[3:]
    Y = np.eye(4)
    Y[:3, :3], Y[:3, 3] = ry, ty
    Z = np.eye(4)
    Z[:3, :3], Z[:3, 3] = rz, tz
    X = np.linalg.inv(Y)
    X[:3, :3] = _orthonormal(X[:3, :3])
    z_pose = _pose_from_matrix(Z)
    x_pose = _pose_from_matrix(X)
    return z_pose, x_pose


def start_effects(data: CalibrationData, free: tuple[str, ...], init) -> Effects:
    """The effects a fit starts from: `init`'s values (a `CalibrationResult`), zero
    without one; with the dictionary's terms among `free` and those of `init` that are
    non-zero. A term at zero outside `free` adds nothing to the model; left out, fits in
    one space compile once whatever their start carried (the refit of a search from a fit
    in a wider space, and the held-out fits from that refit)."""
    init_terms = [
        n
        for n, v in (init.effects.items() if init is not None else ())
        if n not in EFFECT_NAMES and (n in free or np.any(np.asarray(v) != 0))
    ]
    effects = Effects.zeros(
        data.robot.n_joints, tuple(dict.fromkeys((*dictionary_terms(free), *init_terms)))
    )
    if init is not None:
        for k, v in init.effects.items():
            if k in EFFECT_NAMES or k in effects.terms:
                effects = effects.with_value(k, v)
    return effects


def start_poses(
    data: CalibrationData, effects: Effects, init, say: Callable[[str], None]
) -> tuple[np.ndarray, np.ndarray]:
    """``(camera_from_base, flange_from_tool)`` (``wxyz_xyz``) a fit starts from: `init`'s
    (a `CalibrationResult`), else the closed form (`closed_form_start`) from the static
    dwells at the reference constellation."""
    say(f"{data.n_frames} frames, {data.n_leds} LEDs: closed-form initialisation")
    if init is not None:
        return _wxyz_xyz(init.camera_from_base), _wxyz_xyz(init.flange_from_tool)
    cft, bff, _ = pose_pairs(data, effects, data.reference)
    return closed_form_start(cft, bff, data.nominal_flange_from_tool)


def _wxyz_xyz(pose: Pose) -> np.ndarray:
    return np.concatenate([np.asarray(pose.quaternion_wxyz), np.asarray(pose.position)]).astype(
        np.float64
    )
