"""Where the gap of a calibration fit lives, variable by variable (`_localisation` on a
recording): the channels of each observation (the camera axes, and its displacement per
radian of each joint angle), the nuisance refitted with every function (the rigid
transforms and the fit's estimated effects, to first order), the frames used, and the
ranking with its words."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..recording import Recording
from ._localisation import Moments, basis, heldout_fraction, merged, moments
from ._residual_stats import aligned

#: frames the localisation uses at most (evenly spaced): its time stays bounded on long
#: recordings (~1 s), and 10 000 frames of ~10 LEDs determine a fraction to a percent
MAX_FRAMES = 10_000
#: frames whose moments are computed at a time (memory)
CHUNK_FRAMES = 2_000
#: entries of the fit's estimated effects refitted with each function at most (each one
#: prediction of the recording, `predict_residuals`); those beyond (a map's many knots)
#: stay as fitted
MAX_EFFECT_ENTRIES = 32
#: the change of an effect entry whose first-order change of the prediction is taken
#: (SI units: rad, m, s, rad/(N·m) …: small enough for the prediction to be linear in it,
#: large against the prediction's rounding, ~1e-9 m)
EFFECT_STEP = 1e-5
#: a fraction this many σ above zero localises the gap (the jackknife over 8 blocks has
#: 7 degrees of freedom: 2σ is one-sided p ≈ 0.04)
SIGNIFICANT_SIGMA = 2.0


@dataclasses.dataclass(frozen=True)
class Localisation:
    """Per variable, the fraction of the held-out gap² that a smooth function of it alone
    removes and that fraction's jackknife σ (`ranking`: (variable, fraction, σ), highest
    fraction first); the gap of the residual over the observations used [m] (noise
    taken out), its floor [m] (below it the gap is noise: a fraction of it counts the
    floor as the gap) and the frames used."""

    ranking: tuple[tuple[str, float, float], ...]
    gap_m: float
    floor_m: float
    frames: int

    @property
    def localised(self) -> list[str]:
        """The variables whose fraction is more than `SIGNIFICANT_SIGMA` σ above zero,
        highest first."""
        return [v for v, f, s in self.ranking if f > SIGNIFICANT_SIGMA * s]

    def words(self, what: str = "the gap") -> str:
        """Where `what` lives, in words: the top variable with its fraction, and the next."""
        if self.gap_m <= self.floor_m:
            return f"{what} is within its floor: nothing to localise"
        if not self.ranking:
            return f"{what} is not localised: no variable varies over the recording"
        (top, f, s), rest = self.ranking[0], self.ranking[1:]
        nxt = f" (next: {label(rest[0][0])} {_percent(*rest[0][1:])})" if rest else ""
        if f > SIGNIFICANT_SIGMA * s:
            how = "mostly" if f >= 0.5 else "partly"
            return (
                f"{what} lives {how} against {label(top)}: a smooth function of it alone "
                f"removes {_percent(f, s)} of the held-out gap{nxt}"
            )
        return (
            f"{what} is not localised by any one variable: the best, {label(top)}, removes "
            f"{_percent(f, s)} of the held-out gap{nxt}"
        )

    def to_json(self) -> dict[str, Any]:
        """``{"gap_m", "floor_m", "frames", "ranking": [{"variable", "fraction",
        "sigma"}]}``, highest fraction first (a fraction that cannot be told: null)."""
        return {
            "gap_m": self.gap_m,
            "floor_m": self.floor_m,
            "frames": self.frames,
            "ranking": [
                {"variable": v, "fraction": _number(f), "sigma": _number(s)}
                for v, f, s in self.ranking
            ],
        }


def label(variable: str) -> str:
    """A variable's name in words ("joint 2" → "joint 2 angle")."""
    parts = variable.split()
    return f"{variable} angle" if len(parts) == 2 and parts[0] == "joint" else variable


def _percent(fraction: float, sigma: float) -> str:
    return f"{100 * fraction:.0f} ± {100 * sigma:.0f} %"


def _number(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def localise(
    rec: Recording,
    calibration,
    residual: np.ndarray,
    weights: np.ndarray,
    var3: np.ndarray,
    variables: dict[str, np.ndarray],
    block: np.ndarray,
    *,
    floor: float = 0.0,
    space: Sequence[str] = (),
    max_frames: int = MAX_FRAMES,
) -> Localisation:
    """Rank `variables` by the fraction of the held-out gap of `residual` that a smooth
    function of each alone removes (`robtraj.analysis._localisation`).

    **Arguments:**

    - `calibration`: the fit whose residual it is (its `led_ids` order, camera←base and
      clock offset give each observation's displacement per radian of each joint).
    - `residual`: `(N, M, 3)` [m] in `calibration.led_ids` order, NaN where there is none.
    - `weights`, `var3`: `(N, M)` the fit's weights [1/m²] and 3σ̂² [m²] in that order.
    - `variables`: `(N, M)` values per variable in the recording's LED columns
      (`frame_variables`); one that is the same for every LED of a frame is a variable
      of the frame, its function moves the residual along the camera axes (an LED
      displacement in a fixed direction) or along one joint's angle (that joint's
      angle error), whichever the training fold prefers; one of the observation (LED,
      emission angle, LED distance) along the camera axes only (a joint angle error is
      the same for every LED of a frame).
    - `block`: `(N,)` the held-out check's time block of each frame (`HeldOut.block`);
      alternate blocks are the folds.
    - `floor`: the gap's floor [m]; a gap below it counts as the floor.
    - `space`: that of the fit which made `calibration` (its kernels serve the
      predictions of `effect_directions`).
    - `max_frames`: frames used at most, evenly spaced.

    Each function is fitted with the nuisance: the first-order changes of the
    prediction under camera←base and flange←tool (`nuisance_directions`) and under each
    entry of the effects `calibration` estimated (`effect_directions`), the linearised
    refit of the model with the function added.
    """
    um = unit_moments(
        rec, calibration, residual, weights, var3, block, space=space, max_frames=max_frames
    )
    frames, use, per_frame, per_obs = um.frames, um.use, um.per_frame, um.per_obs
    n_joints = per_frame.bw.shape[1] - 3
    seen = np.flatnonzero(use.reshape(-1))
    floor2 = floor**2
    # a displacement in a fixed direction, or one joint's angle error
    frame_groups = [(0, 1, 2), *((3 + j,) for j in range(n_joints))]
    ranking = []
    for name, values in variables.items():
        v = aligned(rec, calibration, np.asarray(values)[frames]).astype(float)
        of_frame = _frame_values(v, use)
        if of_frame is not None:
            b, mom, groups = basis(of_frame), per_frame, frame_groups
        else:
            b, mom, groups = basis(v.reshape(-1)[seen]), per_obs, None
        if b is not None:
            ranking.append((name, *heldout_fraction(mom, b, groups, floor2)))
    ranking.sort(key=lambda x: -x[1] if np.isfinite(x[1]) else np.inf)
    gap2 = per_frame.excess.sum() / max(per_frame.count.sum(), 1)
    return Localisation(
        tuple(ranking), float(np.sqrt(max(gap2, 0.0))), float(floor), int(frames.size)
    )


@dataclasses.dataclass(frozen=True)
class UnitMoments:
    """A fit's residual reduced to the normal-equation moments the localisation fits on
    (`_localisation.Moments`): the recording `frames` used `(F,)`, which observations of
    them count `use` `(F, M)`, their moments per frame (`per_frame`; channels: the three
    camera axes, then each joint's angle, [m per m] and [m per rad]) and per observation
    (`per_obs`, the camera axes; None when not asked for). The nuisance of both: camera←base,
    flange←tool and the fit's estimated effects, to first order."""

    frames: np.ndarray
    use: np.ndarray
    per_frame: Moments
    per_obs: Moments | None


def unit_moments(
    rec: Recording,
    calibration,
    residual: np.ndarray,
    weights: np.ndarray,
    var3: np.ndarray,
    block: np.ndarray,
    *,
    space: Sequence[str] = (),
    max_frames: int = MAX_FRAMES,
    per_observation: bool = True,
) -> UnitMoments:
    """The `UnitMoments` of `residual` of the fit `calibration` (arguments as `localise`),
    on at most `max_frames` frames, evenly spaced."""
    n = rec.n_frames
    frames = np.arange(0, n, max(1, -(-n // max_frames)))
    r, w, v3 = residual[frames], weights[frames], var3[frames]
    use = np.isfinite(r[..., 0]) & np.isfinite(v3) & (w > 0)
    # the model's LED positions: measured − residual
    positions = aligned(rec, calibration, np.asarray(rec.positions[frames])) - r
    sens, camera_from_tool = joint_sensitivities(rec, calibration, frames, positions)
    effects = effect_directions(rec, calibration, frames, space)
    blk = np.asarray(block)[frames]
    n_blocks = int(np.max(block)) + 1
    per_frame, per_obs = [], []
    for c in np.array_split(np.arange(frames.size), -(-frames.size // CHUNK_FRAMES)):
        channels = np.concatenate(
            [np.broadcast_to(np.eye(3), (*use[c].shape, 3, 3)), np.swapaxes(sens[c], -1, -2)], -1
        )
        nuisance = np.concatenate(
            [nuisance_directions(positions[c], camera_from_tool[c]), effects[c]], -1
        )
        per_frame.append(moments(r[c], w[c], v3[c], channels, nuisance, blk[c], n_blocks))
        if not per_observation:
            continue
        seen = use[c].reshape(-1)
        per_obs.append(
            moments(
                r[c].reshape(-1, 1, 3)[seen],
                w[c].reshape(-1, 1)[seen],
                v3[c].reshape(-1, 1)[seen],
                np.broadcast_to(np.eye(3), (int(seen.sum()), 1, 3, 3)),
                nuisance.reshape(-1, 1, 3, nuisance.shape[-1])[seen],
                np.repeat(blk[c], use.shape[1])[seen],
                n_blocks,
            )
        )
    return UnitMoments(frames, use, merged(per_frame), merged(per_obs) if per_observation else None)


def _frame_values(values: np.ndarray, use: np.ndarray) -> np.ndarray | None:
    """`values` `(F, M)` as one value per frame `(F,)` (NaN for a frame without
    observations) when it is the same for every observation of each frame; else None."""
    first = np.argmax(use, axis=1)
    ref = values[np.arange(values.shape[0]), first]
    same = (values == ref[:, None]) | (np.isnan(values) & np.isnan(ref)[:, None]) | ~use
    if not same.all():
        return None
    return np.where(use.any(1), ref, np.nan)


def joint_sensitivities(
    rec: Recording, calibration, frames: np.ndarray, positions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """`(F, M, joints, 3)` the displacement [m/rad] in the camera frame of each LED
    observation of `frames` per radian of error of each joint's angle:
    ``R_cb · (zⱼ × (p − oⱼ))`` with ``p`` the LED in the base frame, ``zⱼ``, ``oⱼ``
    joint j's axis and origin (`robtraj.model.joint_frames` of the recording's robot
    at its logged angles, at robot time t + τ) and ``R_cb`` camera←base's rotation;
    `positions` `(F, M, 3)` the LEDs in the camera frame [m] as the model predicts them
    (NaN give NaN).
    The first-order change of `robtraj.estimate.calibration.predict_residuals` per
    radian of `joint_offset`, with a minus sign.

    Also `(F, 4, 4)` camera←tool of each frame by the nominal kinematics."""
    import jax.numpy as jnp
    import jaxlie

    from ..model import interpolate_joints, robot_from_log

    robot = robot_from_log(rec.robot)
    t = np.asarray(rec.time, float)[frames] + calibration.time_offset
    q = interpolate_joints(
        jnp.asarray(rec.robot.time, float), jnp.asarray(rec.robot.joints, float), jnp.asarray(t)
    )
    cam = _matrix(calibration.camera_from_base)
    rot = cam[:3, :3]
    base = (positions - cam[:3, 3]) @ rot  # Rᵀ(p − t)
    frame = np.asarray(_joint_frames()(jnp.asarray(robot.dh, float), q))
    axis, origin = frame[:, None, :-1, :3, 2], frame[:, None, :-1, :3, 3]
    sens = np.cross(axis, base[:, :, None, :] - origin) @ rot.T
    last_from_flange = np.asarray(jaxlie.SE3(jnp.asarray(robot.last_from_flange)).as_matrix())
    tool = cam @ frame[:, -1] @ last_from_flange @ _matrix(calibration.flange_from_tool)
    return sens, tool


def nuisance_directions(positions: np.ndarray, camera_from_tool: np.ndarray) -> np.ndarray:
    """`(F, M, 3, 12)` the first-order displacement [m per m or rad] of each LED
    observation under a change of camera←base (a translation along and a turn about
    each camera axis through the camera's origin) and of flange←tool (a translation
    along and a turn about each tool axis through the tool's origin), from the LEDs'
    `positions` `(F, M, 3)` and `camera_from_tool` `(F, 4, 4)`: what a refit of the
    rigid transforms absorbs."""
    eye = np.eye(3)
    p = positions[..., None, :]  # (F, M, 1, 3)
    turn_camera = np.cross(eye, p)  # e_a × p, (F, M, 3 axes, 3)
    tool_axes = np.swapaxes(camera_from_tool[:, :3, :3], -1, -2)[:, None]  # (F, 1, a, 3)
    arm = p - camera_from_tool[:, None, None, :3, 3]
    turn_tool = np.cross(tool_axes, arm)
    shift_tool = np.broadcast_to(tool_axes, turn_tool.shape)
    shift_camera = np.broadcast_to(eye, turn_camera.shape)
    cols = np.concatenate([shift_camera, turn_camera, shift_tool, turn_tool], axis=-2)
    return np.swapaxes(cols, -1, -2)


def effect_directions(
    rec: Recording, calibration, frames: np.ndarray, space: Sequence[str] = ()
) -> np.ndarray:
    """`(F, M, 3, P)` the first-order change of the prediction [m per unit] of each LED
    observation of `frames` under each entry of the effects `calibration` estimated (the
    first `MAX_EFFECT_ENTRIES`), by forward differences of the public
    `robtraj.estimate.calibration.predict_residuals` (`space`: that of the fit)."""
    from ..estimate.calibration import predict_residuals

    entries = [
        (e, i)
        for e in calibration.estimated
        for i in range(np.size(calibration.effects.get(e, ())))
    ][:MAX_EFFECT_ENTRIES]
    n_leds = len(calibration.led_ids)
    if not entries:
        return np.zeros((frames.size, n_leds, 3, 0))
    base = predict_residuals(rec, calibration, space)[frames]
    out = []
    for e, i in entries:
        value = np.array(calibration.effects[e], float)
        value.flat[i] += EFFECT_STEP
        moved = dataclasses.replace(calibration, effects={**calibration.effects, e: value})
        out.append((base - predict_residuals(rec, moved, space)[frames]) / EFFECT_STEP)
    return np.stack(out, -1)


def _matrix(pose) -> np.ndarray:
    """A `Pose` as a 4×4 homogeneous matrix."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    w, x, y, z = np.asarray(pose.quaternion_wxyz, float)
    out[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    out[:3, 3] = np.asarray(pose.position, float)
    return out


@functools.cache
def _joint_frames():
    """`robtraj.model.joint_frames` over frames of joint angles, compiled once per shape."""
    import jax

    from ..model import joint_frames

    return jax.jit(jax.vmap(joint_frames, in_axes=(None, 0)))
