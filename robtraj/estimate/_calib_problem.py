"""The bundle-calibration least-squares problem: parameters, residuals, chunked normal equations.

Parameters (`BundleParams`) are tangent-space corrections around the current values held
in the `BundleProblem` (the optimistix ``args``): camera←base and flange←tool are
``current @ SE3.exp(delta)`` (jaxlie tangent order ``[tx, ty, tz, rx, ry, rz]``), the
constellation is ``current + reshape(gauge_basis @ coefficients)`` and the free effects
are ``current + delta``. Residuals are ``sqrt(w) · (measured − predicted)`` per LED
coordinate, through the one forward model of `robtraj.model`.

For whole recordings the normal equations ``JᵀJ``, ``Jᵀr`` are accumulated chunk by chunk
(`lax.scan` over chunks of frames, `jax.jacfwd` inside a chunk), never materialising the
Jacobian. The constellation enters each residual only through its own LED, so its
columns are obtained with three forward-mode tangents (x, y, z of every LED at once)
and accumulated as per-LED blocks.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float

from ..model import (
    Effects,
    RobotModel,
    camera_from_base_at,
    emission_angle,
    flange_poses,
    interpolate_joints,
    led_positions,
)

#: effects that change the flange pose (the forward kinematics must be re-run per step)
KINEMATIC_EFFECTS = ("time_offset", "joint_offset", "link_length", "joint_compliance", "backlash")
#: effects that act on the LED positions given the tool pose
LED_EFFECTS = ("led_angle_bias", "tracker_scale")


class BundleParams(eqx.Module):
    """Free parameters: corrections around the current values of a `BundleProblem`.

    - `camera_from_base`, `flange_from_tool`: `(6,)` SE3 tangent (right perturbation).
    - `constellation`: `(c,)` coefficients of the gauge basis (LED position corrections).
    - `effects`: `(e,)` corrections of the free effects, flattened in `EFFECT_NAMES` order.
    """

    camera_from_base: Float[Array, "6"]
    flange_from_tool: Float[Array, "6"]
    constellation: Float[Array, " c"]
    effects: Float[Array, " e"]


class Frames(eqx.Module):
    """Per-frame data, `(chunks, chunk, ...)` or `(frames, ...)`."""

    time: Float[Array, "*f"]
    direction: Float[Array, "*f joints"]
    drift: Float[Array, "*f"]
    measured: Float[Array, "*f leds 3"]
    sqrt_weight: Float[Array, "*f leds"]
    base_from_flange: Float[Array, "*f 7"]  # used when no kinematic effect is free


class BundleProblem(eqx.Module):
    """Everything but the free parameters (the ``args`` of the residual function)."""

    robot: RobotModel
    camera_from_base: Float[Array, "7"]  # current wxyz_xyz
    flange_from_tool: Float[Array, "7"]
    constellation: Float[Array, "leds 3"]  # current LED positions in the tool frame
    gauge_basis: Float[Array, "leds3 c"]
    normals: Float[Array, "leds 3"]
    effects: Effects  # current values of all effects (free and fixed)
    log_time: Float[Array, " k"]
    joints: Float[Array, "k joints"]
    free: tuple[str, ...] = eqx.field(static=True)
    kinematic: bool = eqx.field(static=True)
    rigid_leds: bool = eqx.field(static=True, default=False)


def effect_sizes(effects: Effects, free: tuple[str, ...]) -> list[int]:
    return [int(np.size(getattr(effects, n))) for n in free]


def apply_effects(effects: Effects, free: tuple[str, ...], delta: Array) -> Effects:
    i = 0
    for name in free:
        old = getattr(effects, name)
        new = old + delta[i : i + old.size].reshape(old.shape)
        effects = eqx.tree_at(lambda e, name=name: getattr(e, name), effects, new)
        i += old.size
    return effects


def _split(g: Array, problem: BundleProblem):
    cfb = jaxlie.SE3(problem.camera_from_base) @ jaxlie.SE3.exp(g[:6])
    fft = jaxlie.SE3(problem.flange_from_tool) @ jaxlie.SE3.exp(g[6:12])
    eff = apply_effects(problem.effects, problem.free, g[12:])
    return cfb, fft, eff


def tool_poses(
    g: Array, problem: BundleProblem, frames: Frames, base_from_flange: jaxlie.SE3 | None = None
) -> tuple[jaxlie.SE3, Effects]:
    """camera←tool per frame (the model's `predict_tool_poses`, with cached FK when
    no kinematic effect is free, or the given `base_from_flange`)."""
    cfb, fft, eff = _split(g, problem)
    if base_from_flange is not None:
        pass
    elif problem.kinematic:
        q = interpolate_joints(problem.log_time, problem.joints, frames.time + eff.time_offset)
        base_from_flange = flange_poses(problem.robot, eff, q, frames.direction)
    else:
        base_from_flange = jaxlie.SE3(frames.base_from_flange)
    cam = camera_from_base_at(cfb, eff, frames.drift)
    return cam @ base_from_flange @ fft, eff


def predict(g: Array, p: Array, problem: BundleProblem, frames: Frames) -> Array:
    """Predicted LED positions `(frames, leds, 3)` [m] in the camera frame."""
    tool, eff = tool_poses(g, problem, frames)
    return led_positions(tool, eff, p, problem.normals)


def flat_global(params: BundleParams) -> Array:
    return jnp.concatenate([params.camera_from_base, params.flange_from_tool, params.effects])


def constellation_of(params: BundleParams, problem: BundleProblem) -> Array:
    return problem.constellation + (problem.gauge_basis @ params.constellation).reshape(-1, 3)


def residuals(params: BundleParams, problem: BundleProblem, frames: Frames) -> Float[Array, " r"]:
    """Weighted residuals ``sqrt(w)·(measured − predicted)``, flattened `(frames·leds·3,)`.

    Pure, optimistix-compatible with ``args = (problem, frames)`` via `residual_fn`.
    """
    pred = predict(flat_global(params), constellation_of(params, problem), problem, frames)
    return (frames.sqrt_weight[..., None] * (frames.measured - pred)).reshape(-1)


def residual_fn(params: BundleParams, args: tuple[BundleProblem, Frames]) -> Array:
    return residuals(params, *args)


def _tool_jacobian(g, problem, frames) -> tuple[jaxlie.SE3, Array]:
    """camera←tool per frame and ``∂ξ/∂g`` `(C, 6, q)` of its tangent ``T(g) = T(0) exp(ξ)``.

    The pose columns are taken with the flange poses held fixed, so that only the
    effect columns push tangents through the forward kinematics.
    """
    if problem.kinematic:
        _, _, eff = _split(g, problem)
        q = interpolate_joints(problem.log_time, problem.joints, frames.time + eff.time_offset)
        fl0 = flange_poses(problem.robot, eff, q, frames.direction)
    else:
        fl0 = jaxlie.SE3(frames.base_from_flange)
    tool0, _ = tool_poses(g, problem, frames, fl0)

    def xi(tool):
        return jax.vmap(lambda a, b: (a.inverse() @ b).log())(tool0, tool)

    # pose columns at g = 0 (the problem is re-centred after every step): with
    # T = S·cfb·exp(δc)·F·fft·exp(δf) (S the thermal shift), ξ = Ad((F·fft)⁻¹)·δc + δf
    fft0 = jaxlie.SE3(problem.flange_from_tool)
    ad = jax.vmap(lambda f: (f @ fft0).inverse().adjoint())(fl0)  # (C, 6, 6)
    j_pose = jnp.concatenate([ad, jnp.broadcast_to(jnp.eye(6, dtype=ad.dtype), ad.shape)], -1)
    if g.shape[0] == 12:
        return tool0, j_pose
    j_eff = jax.jacfwd(lambda ge: xi(tool_poses(g.at[12:].set(ge), problem, frames)[0]))(g[12:])
    return tool0, jnp.concatenate([j_pose, j_eff], -1)


def _led_effect_columns(problem: BundleProblem) -> list[int]:
    """Indices in g of effect entries that act on the LED positions directly."""
    cols, i = [], 12
    for name, size in zip(problem.free, effect_sizes(problem.effects, problem.free)):
        if name in LED_EFFECTS:
            cols += list(range(i, i + size))
        i += size
    return cols


def _chunk_terms(g, p, problem, frames):
    """Per-chunk contributions to the normal equations in the ``[g, vec(p)]`` coordinates.

    Two-stage chain rule (forward mode): per frame, the tool-pose tangent ξ of
    ``T(g) = T(0) exp(ξ)`` w.r.t. g (q tangents, per frame only); per LED, the LED
    position w.r.t. ξ (6 tangents), w.r.t. the LED-level effects and w.r.t. its own
    constellation entry (3 tangents).
    """
    tool0, tool_g = _tool_jacobian(g, problem, frames)
    eff0 = apply_effects(problem.effects, problem.free, g[12:])
    led_cols = _led_effect_columns(problem)

    def leds(xi, p_, g_led):
        eff = eff0
        if led_cols:
            gg = g.at[jnp.asarray(led_cols)].set(g_led)
            eff = apply_effects(problem.effects, problem.free, gg[12:])
        tool = jax.vmap(lambda t, x: t @ jaxlie.SE3.exp(x))(tool0, xi)
        return led_positions(tool, eff, p_, problem.normals)

    xi0 = jnp.zeros(frames.time.shape + (6,), g.dtype)
    g_led = g[jnp.asarray(led_cols, int)] if led_cols else jnp.zeros(0, g.dtype)
    pred = leds(xi0, p, g_led)
    eye6 = jnp.eye(6, dtype=g.dtype)

    def t_xi(a):
        return jax.jvp(
            lambda x: leds(x, p, g_led), (xi0,), (jnp.broadcast_to(eye6[a], xi0.shape),)
        )[1]

    jac_xi = jnp.stack([t_xi(a) for a in range(6)], axis=-1)  # (C, M, 3, 6)
    jac_g = jnp.einsum("cmia,cag->cmig", jac_xi, tool_g)
    if led_cols:
        jl = jax.jacfwd(lambda gl: leds(xi0, p, gl))(g_led)  # (C, M, 3, L)
        jac_g = jac_g.at[..., jnp.asarray(led_cols)].add(jl)
    eye3 = jnp.eye(3, dtype=p.dtype)

    def t_p(a):
        return jax.jvp(
            lambda pp: leds(xi0, pp, g_led), (p,), (jnp.broadcast_to(eye3[a], p.shape),)
        )[1]

    jac_p = jnp.stack([t_p(a) for a in range(3)], axis=-1)  # (C, M, 3, 3)
    sw = frames.sqrt_weight[..., None]
    r = sw * (frames.measured - pred)
    jg = sw[..., None] * jac_g
    jp = sw[..., None] * jac_p
    return (
        jnp.einsum("cmiq,cmir->qr", jg, jg),
        jnp.einsum("cmiq,cmia->qma", jg, jp),
        jnp.einsum("cmia,cmib->mab", jp, jp),
        jnp.einsum("cmiq,cmi->q", jg, r),
        jnp.einsum("cmia,cmi->ma", jp, r),
        jnp.sum(r * r),
    )


def _skew(v: Array) -> Array:
    z = jnp.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return jnp.stack(
        [jnp.stack([z, -w, y], -1), jnp.stack([w, z, -x], -1), jnp.stack([-y, x, z], -1)], -2
    )


def _chunk_terms_rigid(g, p, problem, frames):
    """`_chunk_terms` for LEDs that move rigidly with the tool (no LED-level effect).

    With ``y = T exp(ξ) p``: ``∂y/∂ξ = R [I, −[p]×]`` and ``∂y/∂p = R``, so the rotation
    cancels in every product and the per-frame 6×6 blocks are weighted moments of the
    constellation. Same result as the forward-mode path, an order of magnitude faster.
    """
    tool0, tg = _tool_jacobian(g, problem, frames)
    rot = jax.vmap(lambda t: t.rotation().as_matrix())(tool0)  # (C, 3, 3)
    pred = jnp.einsum("cij,mj->cmi", rot, p) + tool0.translation()[:, None, :]
    w = frames.sqrt_weight**2
    e = frames.measured - pred
    u = jnp.einsum("cji,cmj->cmi", rot, e)  # residual in the tool frame
    s0 = w.sum(1)
    s1 = w @ p
    s2 = jnp.einsum("cm,mi,mj->cij", w, p, p)
    eye = jnp.eye(3, dtype=p.dtype)
    k = _skew(s1)
    a_rot = jnp.trace(s2, axis1=1, axis2=2)[:, None, None] * eye - s2
    a = jnp.concatenate(
        [
            jnp.concatenate([s0[:, None, None] * eye, -k], -1),
            jnp.concatenate([k, a_rot], -1),
        ],
        -2,
    )  # (C, 6, 6)
    b_xi = jnp.concatenate(
        [jnp.einsum("cm,cmi->ci", w, u), jnp.einsum("cm,cmi->ci", w, jnp.cross(p[None], u))], -1
    )
    hgg = jnp.einsum("caq,cab,cbr->qr", tg, a, tg)
    kk = jnp.einsum("cm,caq->maq", w, tg)  # (M, 6, q)
    blk = jnp.concatenate([jnp.broadcast_to(eye, p.shape[:1] + (3, 3)), _skew(p)], -2)  # (M,6,3)
    hgp = jnp.einsum("maq,mab->qmb", kk, blk)
    hpp = w.sum(0)[:, None, None] * eye
    bg = jnp.einsum("caq,ca->q", tg, b_xi)
    bp = jnp.einsum("cm,cmi->mi", w, u)
    return hgg, hgp, hpp, bg, bp, jnp.sum(w * jnp.sum(e * e, -1))


@eqx.filter_jit
def normal_equations(g: Array, p: Array, problem: BundleProblem, chunks: Frames):
    """Accumulate ``(Hgg, Hgp, Hpp, bg, bp, cost)`` over all chunks (`lax.scan`)."""
    q, m = g.shape[0], p.shape[0]
    z = jnp.zeros
    init = (z((q, q)), z((q, m, 3)), z((m, 3, 3)), z(q), z((m, 3)), z(()))

    terms_fn = _chunk_terms_rigid if problem.rigid_leds else _chunk_terms

    def body(acc, frames):
        terms = terms_fn(g, p, problem, frames)
        return tuple(a + t for a, t in zip(acc, terms)), None

    acc, _ = jax.lax.scan(body, init, chunks)
    return acc


def _predict_any(g, p, problem, frames):
    if not problem.rigid_leds:
        return predict(g, p, problem, frames)
    tool, _ = tool_poses(g, problem, frames)
    rot = jax.vmap(lambda t: t.rotation().as_matrix())(tool)
    return jnp.einsum("cij,mj->cmi", rot, p) + tool.translation()[:, None, :]


@eqx.filter_jit
def cost(g: Array, p: Array, problem: BundleProblem, chunks: Frames) -> Array:
    """Weighted residual sum of squares over all chunks."""

    def body(acc, frames):
        pred = _predict_any(g, p, problem, frames)
        r = frames.sqrt_weight[..., None] * (frames.measured - pred)
        return acc + jnp.sum(r * r), None

    acc, _ = jax.lax.scan(body, jnp.zeros(()), chunks)
    return acc


@eqx.filter_jit
def evaluate(g: Array, p: Array, problem: BundleProblem, chunks: Frames):
    """Per observation: unweighted residual `(frames, leds, 3)` [m] and emission angle [rad]."""

    def body(_, frames):
        tool, eff = tool_poses(g, problem, frames)
        rot = jax.vmap(lambda t: t.rotation().as_matrix())(tool)
        if problem.rigid_leds:
            pred = jnp.einsum("cij,mj->cmi", rot, p) + tool.translation()[:, None, :]
        else:
            pred = led_positions(tool, eff, p, problem.normals)
        nrm = jnp.einsum("cij,mj->cmi", rot, problem.normals)
        return None, (frames.measured - pred, emission_angle(pred, nrm))

    _, (d, theta) = jax.lax.scan(body, None, chunks)
    return d.reshape(-1, *d.shape[2:]), theta.reshape(-1, theta.shape[-1])


@eqx.filter_jit
def fixed_flange_poses(robot: RobotModel, effects: Effects, log_time, joints, chunks: Frames):
    """base←flange per frame (`wxyz_xyz`, chunked) for fixed kinematic effects."""

    def body(_, frames):
        q = interpolate_joints(log_time, joints, frames.time + effects.time_offset)
        return None, flange_poses(robot, effects, q, frames.direction).wxyz_xyz

    _, out = jax.lax.scan(body, None, chunks)
    return out
