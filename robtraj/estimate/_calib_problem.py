"""The bundle-calibration least-squares problem: parameters, residuals, chunked normal equations.

Parameters θ = [g, c] are corrections around the current values held in the
`BundleProblem`: g holds camera←base and flange←tool as ``current @ SE3.exp(δ)`` (jaxlie
tangent order ``[tx, ty, tz, rx, ry, rz]``) and the free effects as ``current + δ``; c
the coefficients of the constellation basis (``current + reshape(basis @ c)``).
Residuals are ``sqrt(w) · (measured − predicted)`` per LED coordinate, through the one
forward model of `robtraj.model` (`residuals`); probe poses add 6-DOF pose residuals.
`bundle_normal` is the problem as `robtraj.estimate._solve` takes it.

For whole recordings the normal equations ``JᵀJ``, ``Jᵀr`` are accumulated chunk by chunk,
never materialising the Jacobian: one compiled kernel per block of frames read from the
recording (`lax.scan` over its chunks, `_calib_frames.TrackerFrames`), its sums carried
from block to block in the order of the chunks, so that the blocking does not change
them; `bundle_normal` is a host loop over the blocks (`composed`). The effects'
columns of the tool pose come in closed form from the kinematics' own twists
(`robtraj.model.flange_jacobian`), not by forward mode through the forward kinematics.
The constellation enters each residual only through its own LED, so its
columns are obtained with three forward-mode tangents (x, y, z of every LED at once)
and accumulated as per-LED blocks.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float, Int

from ..jax_ops import se3_right_jacobian
from ..model import (
    Effects,
    RobotModel,
    camera_from_base_at,
    dh_corrections,
    effective_joints,
    emission_angle,
    flange_jacobian,
    flange_poses,
    interpolate_joints,
    joint_term_features,
    joint_term_joints,
    led_positions,
    motion_direction,
    motion_sign,
    term,
)
from . import _calib_frames
from ._calib_data import CalibrationData
from ._calib_frames import TrackerFrames, Weights
from ._pose_normal import normal_terms
from ._prior import GaussianPrior, no_prior
from ._probe_error import probe_pose_error
from ._solve import composed

#: effects that change the flange pose (the forward kinematics must be re-run per step)
KINEMATIC_EFFECTS = (
    "time_offset",
    "joint_offset",
    "link_length",
    "link_twist",
    "joint_compliance",
    "backlash",
)
#: effects that act on the LED positions given the tool pose
LED_EFFECTS = ("led_angle_bias", "tracker_scale")


class Frames(eqx.Module):
    """Per-frame data, `(chunks, chunk, ...)` or `(frames, ...)`."""

    time: Float[Array, "*f"]
    direction: Float[Array, "*f joints"]
    moving: Float[Array, "*f joints"]  # sign of the joint velocities, 0 at rest
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
    normals: Float[Array, "leds 3"]
    effects: Effects  # current values of all effects (free and fixed)
    log_time: Float[Array, " k"]
    joints: Float[Array, "k joints"]
    free: tuple[str, ...] = eqx.field(static=True)
    kinematic: bool = eqx.field(static=True)
    rigid_leds: bool = eqx.field(static=True, default=False)
    #: on the rigid path, the columns of the LED-level effects in `free` (at zero) are
    #: taken too (the score test's normal equations); a fit that holds them skips them
    led_columns: bool = eqx.field(static=True, default=False)
    #: the frames are the log's entries, one static pose each (6-DOF pose series): the
    #: joints are read, not interpolated, and no clock offset applies
    at_log: bool = eqx.field(static=True, default=False)


def is_kinematic(name: str) -> bool:
    """Whether effect `name` changes the flange pose (library or dictionary joint term)."""
    t = term(name)
    return name in KINEMATIC_EFFECTS or (t is not None and t.kind == "joint")


def is_led_level(name: str) -> bool:
    """Whether effect `name` acts on the LED positions given the tool pose."""
    t = term(name)
    return name in LED_EFFECTS or (t is not None and t.kind == "led")


def effect_sizes(effects: Effects, free: tuple[str, ...]) -> list[int]:
    return [int(np.size(effects.get(n))) for n in free]


def apply_effects(effects: Effects, free: tuple[str, ...], delta: Array) -> Effects:
    i = 0
    for name in free:
        old = effects.get(name)
        effects = effects.replace(name, old + delta[i : i + old.size].reshape(old.shape))
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
        q = _logged_joints(problem, frames.time + eff.time_offset)
        base_from_flange = flange_poses(problem.robot, eff, q, frames.direction, frames.moving)
    else:
        base_from_flange = jaxlie.SE3(frames.base_from_flange)
    cam = camera_from_base_at(cfb, eff, frames.drift)
    return cam @ base_from_flange @ fft, eff


def predict(g: Array, p: Array, problem: BundleProblem, frames: Frames) -> Array:
    """Predicted LED positions `(frames, leds, 3)` [m] in the camera frame."""
    tool, eff = tool_poses(g, problem, frames)
    return led_positions(tool, eff, p, problem.normals)


def _logged_joints(problem: BundleProblem, t: Array) -> Array:
    """The logged joint angles at robot-clock times `t` (`problem.at_log`: the log's own
    entries)."""
    if problem.at_log:
        return problem.joints
    return interpolate_joints(problem.log_time, problem.joints, t)


def _tool_jacobian(g, problem, frames) -> tuple[jaxlie.SE3, Array]:
    """camera←tool per frame and ``∂ξ/∂g`` `(C, 6, q)` of its tangent ``T(g) = T(0) exp(ξ)``.

    The pose columns are taken with the flange poses held fixed; the effect columns
    come in closed form (`_effect_columns`), from one pass of the kinematics.
    """
    kinematics = _kinematic_twists(g, problem, frames) if problem.kinematic else None
    fl0 = kinematics[0] if kinematics else jaxlie.SE3(frames.base_from_flange)
    tool0, _ = tool_poses(g, problem, frames, fl0)

    # pose columns: with T = S·cfb·exp(gc + δc)·F·fft·exp(gf + δf) (S the thermal shift)
    # and exp(g + δ) = exp(g)·exp(Jr(g)·δ), ξ = Ad((F·fft(gf))⁻¹)·Jr(gc)·δc + Jr(gf)·δf
    _, fft, _ = _split(g, problem)
    ad = jax.vmap(lambda f: (f @ fft).inverse().adjoint())(fl0)  # (C, 6, 6)
    jr_c, jr_f = se3_right_jacobian(g[:6]), se3_right_jacobian(g[6:12])
    # a sum over the six tangent entries written out: batches of tiny matrix products
    # are slow on CPU
    ad_jr = sum(ad[:, :, k, None] * jr_c[None, k, :] for k in range(6))
    j_pose = jnp.concatenate([ad_jr, jnp.broadcast_to(jr_f, ad.shape)], -1)
    if g.shape[0] == 12:
        return tool0, j_pose
    j_eff = _effect_columns(g, problem, frames, tool0, ad, kinematics)
    return tool0, jnp.concatenate([j_pose, j_eff], -1)


def _kinematic_twists(g, problem: BundleProblem, frames: Frames):
    """base←flange per frame (the model's `flange_poses`), its twists per link parameter
    (`robtraj.model.flange_jacobian`, `(C, 6, joints, 5)`), and the derivatives of the
    effective joint angles in the clock offset `(C, joints)` [rad/s] and in each joint's
    compliance (the gravity torque, `(C, joints)` [N·m])."""
    _, _, eff = _split(g, problem)
    robot = problem.robot

    def joints(t, compliance):
        e = eqx.tree_at(lambda x: x.joint_compliance, eff, compliance)
        q = _logged_joints(problem, t)
        return jax.vmap(lambda a, d, m: effective_joints(robot, e, a, d, m))(
            q, frames.direction, frames.moving
        )

    t = frames.time + eff.time_offset
    c = eff.joint_compliance
    q_eff, tangent = jax.linearize(joints, t, c)
    rate = tangent(jnp.ones_like(t), jnp.zeros_like(c))
    torque = tangent(jnp.zeros_like(t), jnp.ones_like(c))
    dh_delta, tilt = dh_corrections(robot, eff)
    flange, twist = jax.vmap(lambda a: flange_jacobian(robot, a, dh_delta, tilt))(q_eff)
    return flange, twist, rate, torque, t


def _effect_columns(g, problem: BundleProblem, frames: Frames, tool0, ad, kinematics) -> Array:
    """``∂ξ/∂(effects)`` `(C, 6, q − 12)` in closed form: each kinematic effect moves
    some links' DH parameters, whose flange twists `kinematics` holds (carried to the
    tool frame by `ad`, the adjoint of (flange·tool)⁻¹); the thermal drift translates
    camera←base; LED-level effects do not move the tool."""
    n = frames.time.shape[0]
    if kinematics is not None:
        _, twist, rate, torque, t_robot = kinematics
        dh = jnp.einsum("cab,cbjk->cajk", ad, twist)  # (C, 6, joints, [θ, d, a, α, β])
        turn = dh[..., 0]
    sizes = effect_sizes(problem.effects, problem.free)
    joint_terms = [n for n in problem.free if term(n) is not None and term(n).kind == "joint"]
    cols, order, at = [], [], 0
    for name, size in zip(problem.free, sizes):
        order.append(np.arange(at, at + size))
        at += size
        if name in joint_terms:
            continue
        if name == "time_offset":
            col = jnp.einsum("caj,cj->ca", turn, rate)[..., None]
        elif name == "joint_offset":
            col = turn
        elif name == "backlash":
            col = turn * frames.direction[:, None, :]
        elif name == "joint_compliance":
            col = turn * torque[:, None, :]
        elif name == "link_length":
            col = dh[..., 1:3].reshape(n, 6, -1)
        elif name == "link_twist":
            col = dh[..., 3:5].reshape(n, 6, -1)
        elif name == "thermal_drift":
            # a shift of camera←base by drift·δ, as a tool-frame twist
            ad_tool = jax.vmap(lambda t: t.inverse().adjoint())(tool0)
            col = ad_tool[..., :3] * frames.drift[:, None, None]
        else:  # LED-level effects act on the LED positions, not on the tool pose
            col = jnp.zeros((n, 6, size), g.dtype)
        cols.append(col)
    if not joint_terms:
        return jnp.concatenate(cols, -1)
    # every joint term's columns from one feature array, then put in the order of g
    q_log = _logged_joints(problem, t_robot)
    phi = jax.vmap(lambda a, s, tau: joint_term_features(joint_terms, a, s, tau))(
        q_log, frames.moving, torque
    )  # (C, k)
    cols.append(turn[:, :, joint_term_joints(joint_terms)] * phi[:, None, :])
    rest = [o for name, o in zip(problem.free, order) if name not in joint_terms]
    mine = [o for name, o in zip(problem.free, order) if name in joint_terms]
    perm = np.argsort(np.concatenate(rest + mine))
    return jnp.concatenate(cols, -1)[..., perm]


def _led_effect_columns(problem: BundleProblem) -> list[int]:
    """Indices in g of effect entries that act on the LED positions directly."""
    cols, i = [], 12
    for name, size in zip(problem.free, effect_sizes(problem.effects, problem.free)):
        if is_led_level(name):
            cols += list(range(i, i + size))
        i += size
    return cols


def _chunk_terms(g, p, problem, frames, per_frame=False):
    """Per-chunk contributions to the normal equations in the ``[g, vec(p)]`` coordinates
    (``H`` blocks summed over the chunk, or per frame with `per_frame`; ``b`` per frame:
    `(C, q)` and `(C, m, 3)`).

    Two-stage chain rule (forward mode): per frame, the tool-pose tangent ξ of
    ``T(g) = T(0) exp(ξ)`` w.r.t. g (q tangents, per frame only); per LED, the LED
    position w.r.t. ξ (6 tangents), w.r.t. the LED-level effects and w.r.t. its own
    constellation entry (3 tangents). The products are taken in the frame's local
    coordinates k = [ξ, LED-level effects] first (``Σ_LEDs KᵀWK``, 6 + l square) and
    mapped to g once per frame (``Gᵀ(·)G``), never as a `(frames, LEDs, 3, q)` Jacobian.
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

    k_loc = jnp.stack([t_xi(a) for a in range(6)], axis=-1)  # (C, M, 3, 6)
    # G maps g to the local coordinates: ξ = tool_g · g, the LED-level effects selected
    gmap = tool_g
    if led_cols:
        jl = jax.jacfwd(lambda gl: leds(xi0, p, gl))(g_led)  # (C, M, 3, L)
        k_loc = jnp.concatenate([k_loc, jl], -1)
        sel = jnp.zeros((len(led_cols), g.shape[0]), g.dtype)
        sel = sel.at[jnp.arange(len(led_cols)), jnp.asarray(led_cols)].set(1.0)
        gmap = jnp.concatenate([tool_g, jnp.broadcast_to(sel, tool_g.shape[:1] + sel.shape)], 1)
    eye3 = jnp.eye(3, dtype=p.dtype)

    def t_p(a):
        return jax.jvp(
            lambda pp: leds(xi0, pp, g_led), (p,), (jnp.broadcast_to(eye3[a], p.shape),)
        )[1]

    jac_p = jnp.stack([t_p(a) for a in range(3)], axis=-1)  # (C, M, 3, 3)
    sw = frames.sqrt_weight[..., None]
    r = sw * (frames.measured - pred)
    kw = sw[..., None] * k_loc
    jp = sw[..., None] * jac_p
    # products per frame (and per LED) over the 3 coordinates or the local coordinates
    # written out as sums: batches of tiny matrix products are slow on CPU
    a_loc = jnp.einsum("cmik,cmil->ckl", kw, kw)
    n_loc = sum(kw[:, :, i, :, None] * jp[:, :, i, None, :] for i in range(3))  # (C,M,k,3)
    k_r = sum(kw[:, :, i, :] * r[:, :, i, None] for i in range(3)).sum(1)  # (C, k)
    nk = gmap.shape[1]
    if per_frame:
        a_g = sum(a_loc[:, :, l, None] * gmap[:, None, l, :] for l in range(nk))  # (C, k, q)
        hgg = sum(gmap[:, k, :, None] * a_g[:, k, None, :] for k in range(nk))
        hgp = sum(gmap[:, k, :, None, None] * n_loc[:, None, :, k, :] for k in range(nk))
        hpp = sum(jp[:, :, i, :, None] * jp[:, :, i, None, :] for i in range(3))
    else:
        hgg = jnp.einsum("ckq,ckl,clr->qr", gmap, a_loc, gmap)
        hgp = jnp.einsum("ckq,cmka->qma", gmap, n_loc)
        hpp = jnp.einsum("cmia,cmib->mab", jp, jp)
    return (
        hgg,
        hgp,
        hpp,
        sum(gmap[:, k, :] * k_r[:, k, None] for k in range(nk)),
        sum(jp[:, :, i, :] * r[:, :, i, None] for i in range(3)),
        jnp.sum(r * r),
    )


def _rotate(rot: Float[Array, "c 3 3"], v: Float[Array, "*#c m 3"]) -> Float[Array, "c m 3"]:
    """``rot[c] @ v[c, m]`` for every frame c and LED m, component by component (a batch
    of 3×3 products as one loop, not as tiny matrix products)."""
    if v.ndim == 2:
        v = v[None]
    return jnp.stack([sum(rot[:, i, j, None] * v[..., j] for j in range(3)) for i in range(3)], -1)


def _skew(v: Array) -> Array:
    z = jnp.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return jnp.stack(
        [jnp.stack([z, -w, y], -1), jnp.stack([w, z, -x], -1), jnp.stack([-y, x, z], -1)], -2
    )


def _chunk_terms_rigid(g, p, problem, frames, per_frame=False):
    """`_chunk_terms` where the LEDs move rigidly with the tool (every LED-level effect
    at zero; with `problem.led_columns` they still get their columns, else zeros).

    With ``y = T exp(ξ) p``: ``∂y/∂ξ = R [I, −[p]×]`` and ``∂y/∂p = R``, so the rotation
    cancels in every product and the per-frame 6×6 blocks are weighted moments of the
    constellation. An LED-level effect at zero moves no LED, so these stay exact; its
    own column ``∂y/∂e`` (linear in e: one batched tangent of `led_positions`) is taken
    to the tool frame by ``Rᵀ`` and enters through its products with the above. Same
    result as the forward-mode path, an order of magnitude faster.
    """
    tool0, tg = _tool_jacobian(g, problem, frames)
    rot = jax.vmap(lambda t: t.rotation().as_matrix())(tool0)  # (C, 3, 3)
    w = frames.sqrt_weight**2
    e = frames.measured - _rotate(rot, p) - tool0.translation()[:, None, :]
    u = _rotate(jnp.swapaxes(rot, 1, 2), e)  # residual in the tool frame
    s0 = w.sum(1)
    s1 = w @ p
    s2 = (w @ (p[:, :, None] * p[:, None, :]).reshape(-1, 9)).reshape(-1, 3, 3)
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
    wu = w[..., None] * u
    b_xi = jnp.concatenate([wu.sum(1), jnp.cross(p[None], wu).sum(1)], -1)
    c = "c" if per_frame else ""
    blk = jnp.concatenate([jnp.broadcast_to(eye, p.shape[:1] + (3, 3)), _skew(p)], -2)  # (M,6,3)
    if per_frame:
        # per frame, as sums over the six tangent entries written out: batches of tiny
        # matrix products are slow on CPU
        a_tg = sum(a[:, :, k, None] * tg[:, None, k, :] for k in range(6))  # (C, 6, q)
        hgg = sum(tg[:, k, :, None] * a_tg[:, k, None, :] for k in range(6))
        tg_blk = sum(tg[:, k, :, None, None] * blk[None, None, :, k, :] for k in range(6))
        hgp = w[:, None, :, None] * tg_blk  # (C, q, M, 3)
    else:
        a_tg = sum(a[:, :, k, None] * tg[:, None, k, :] for k in range(6))  # (C, 6, q)
        hgg = jnp.einsum("caq,car->qr", tg, a_tg)
        hgp = jnp.einsum("maq,mab->qmb", jnp.einsum("cm,caq->maq", w, tg), blk)
    hpp = (w if per_frame else w.sum(0))[..., None, None] * eye
    bg = sum(tg[:, k, :] * b_xi[:, k, None] for k in range(6))  # (C, q)
    bp = wu
    led_cols = _led_effect_columns(problem) if problem.led_columns else []
    if led_cols:
        idx = jnp.asarray(led_cols)

        def leds(gl):
            eff = apply_effects(problem.effects, problem.free, g.at[idx].set(gl)[12:])
            return led_positions(tool0, eff, p, problem.normals)

        ke = jax.jacfwd(leds)(g[idx])  # (C, M, 3, L) camera frame
        kt = jnp.einsum("cji,cmjl->cmil", rot, ke)  # tool frame
        wk = w[..., None, None] * kt
        h_exi = jnp.concatenate(
            [wk.sum(1).transpose(0, 2, 1), -jnp.einsum("cmil,mij->clj", wk, _skew(p))], -1
        )  # (C, L, 6): Σ_LEDs w Kᵀ [I, −[p]×]
        h_eg = jnp.einsum(f"clx,cxq->{c}lq", h_exi, tg)  # zero in the LED-level columns
        h_ee = jnp.einsum(f"cmil,cmik->{c}lk", wk, kt)
        hgg = hgg.at[..., idx, :].add(h_eg).at[..., :, idx].add(jnp.swapaxes(h_eg, -1, -2))
        hgg = hgg.at[..., idx[:, None], idx[None, :]].add(h_ee)
        hgp = hgp.at[..., idx, :, :].add(jnp.einsum(f"cmil->{c}lmi", wk))
        bg = bg.at[:, idx].add(jnp.einsum("cmil,cmi->cl", wk, u))
    return hgg, hgp, hpp, bg, bp, jnp.sum(w * jnp.sum(e * e, -1))


def chunk_terms(g, p, problem: BundleProblem, frames: Frames, per_frame: bool = False):
    """One chunk's terms of the normal equations (`_chunk_terms_rigid` where the LEDs move
    rigidly with the tool, else `_chunk_terms`)."""
    fn = _chunk_terms_rigid if problem.rigid_leds else _chunk_terms
    return fn(g, p, problem, frames, per_frame)


def zero_terms(q: int, m: int, n_clusters: int = 0):
    """Zero accumulators of the normal equations' terms (per cluster with `n_clusters`)."""
    shapes = ((q, q), (q, m, 3), (m, 3, 3), (q,), (m, 3))
    acc = (*(jnp.zeros(s) for s in shapes), jnp.zeros(()))
    return acc, tuple(jnp.zeros((n_clusters, *s)) for s in shapes) if n_clusters else ()


@eqx.filter_jit
def normal_block(g: Array, p: Array, problem: BundleProblem, chunks: Frames, acc):
    """``(Hgg, Hgp, Hpp, bg, bp, cost)`` of one block of chunks added to `acc`."""
    return _accumulate(g, p, problem, chunks, None, 0, (acc, ()))[0]


@eqx.filter_jit
def normal_block_clustered(
    g: Array,
    p: Array,
    problem: BundleProblem,
    chunks: Frames,
    cluster: Int[Array, "chunks chunk"],
    n_clusters: int,
    acc,
):
    """`normal_block` and every term summed per cluster of frames (`cluster`: each
    frame's cluster in ``[0, n_clusters)``; padding frames carry no weight), added to
    `acc` = ``(terms, per-cluster terms)``."""
    return _accumulate(g, p, problem, chunks, cluster, n_clusters, acc)


def normal_equations(g: Array, p: Array, problem: BundleProblem, frames: TrackerFrames):
    """Accumulate ``(Hgg, Hgp, Hpp, bg, bp, cost)`` over all frames, block by block."""
    acc = [zero_terms(g.shape[0], p.shape[0])[0]]

    def compute(block):
        acc[0] = normal_block(g, p, problem, _frames(block), acc[0])

    frames.blocks(compute)
    return acc[0]


def normal_equations_clustered(
    g: Array,
    p: Array,
    problem: BundleProblem,
    frames: TrackerFrames,
    cluster: np.ndarray,
    n_clusters: int,
):
    """`normal_equations` and every term summed per cluster of frames: `cluster`
    `(chunks, chunk)` gives each frame's cluster in ``[0, n_clusters)`` (padding frames
    carry no weight). Returns ``((Hgg, Hgp, Hpp, bg, bp, cost), (Hgg, Hgp, Hpp, bg, bp)
    per cluster)`` with a leading cluster axis `(G, ...)` on the latter."""
    acc = [zero_terms(g.shape[0], p.shape[0], n_clusters)]

    def compute(block):
        k = block.a // frames.size
        ids = jnp.asarray(cluster[k : k + frames.per])
        acc[0] = normal_block_clustered(g, p, problem, _frames(block), ids, n_clusters, acc[0])

    frames.blocks(compute)
    return acc[0]


def _frames(block) -> Frames:
    return Frames(**jax.device_put(block.frames))


def _accumulate(g, p, problem, chunks, cluster, n_clusters, start):
    """The terms of `chunks` (`lax.scan` over them) added to `start` = ``(terms,
    per-cluster terms)``, chunk by chunk in order."""

    def body(carry, xs):
        acc, clustered = carry
        frames, ids = xs
        if ids is None:
            hgg, hgp, hpp, bg, bp, cost = chunk_terms(g, p, problem, frames)
            terms = (hgg, hgp, hpp, bg.sum(0), bp.sum(0), cost)
        else:
            frame_terms = chunk_terms(g, p, problem, frames, per_frame=True)
            terms = (*(t.sum(0) for t in frame_terms[:5]), frame_terms[5])
            clustered = tuple(
                c + jax.ops.segment_sum(t, ids, n_clusters)
                for c, t in zip(clustered, frame_terms[:5])
            )
        return (tuple(a + t for a, t in zip(acc, terms)), clustered), None

    (acc, clustered), _ = jax.lax.scan(body, start, (chunks, cluster))
    return acc, clustered


@eqx.filter_jit
def evaluate(g: Array, p: Array, problem: BundleProblem, chunks: Frames):
    """Per observation of a block of chunks: unweighted residual `(frames, leds, 3)` [m]
    and emission angle [rad]."""

    def body(_, frames):
        tool, eff = tool_poses(g, problem, frames)
        rot = jax.vmap(lambda t: t.rotation().as_matrix())(tool)
        if problem.rigid_leds:
            pred = _rotate(rot, p) + tool.translation()[:, None, :]
        else:
            pred = led_positions(tool, eff, p, problem.normals)
        nrm = _rotate(rot, problem.normals)
        return None, (frames.measured - pred, emission_angle(pred, nrm))

    _, (d, theta) = jax.lax.scan(body, None, chunks)
    return d.reshape(-1, *d.shape[2:]), theta.reshape(-1, theta.shape[-1])


@eqx.filter_jit
def fixed_flange_poses(robot: RobotModel, effects: Effects, log_time, joints, chunks: Frames):
    """base←flange per frame (`wxyz_xyz`, chunked) for fixed kinematic effects."""

    def body(_, frames):
        q = interpolate_joints(log_time, joints, frames.time + effects.time_offset)
        return None, flange_poses(robot, effects, q, frames.direction, frames.moving).wxyz_xyz

    _, out = jax.lax.scan(body, None, chunks)
    return out


def flange_poses_of(problem: BundleProblem, frames: TrackerFrames) -> np.ndarray:
    """base←flange `(frames, 7)` ``wxyz_xyz`` of every frame at `problem`'s effects (held
    fixed: the fit's flange poses when no kinematic effect is free)."""
    out = np.empty((frames.n_frames, 7))
    args = (problem.robot, problem.effects, problem.log_time, problem.joints)

    def compute(block):
        return fixed_flange_poses(*args, _frames(block))

    def collect(block, poses):
        out[block.a : block.b] = np.asarray(poses).reshape(-1, 7)[: block.b - block.a]

    frames.replace(weights=Weights()).blocks(compute, collect, read=False)
    return out


def over_residuals(bundle: BundleData, q: int, visit) -> None:
    """``visit(block, d, theta)`` for every block of frames in order: the residuals at
    the problem's current values (θ = 0) of the block's frames (NumPy, padding cut),
    unweighted `(frames, leds, 3)` [m], and their emission angles [rad]."""
    g, p, problem = jnp.zeros(q), bundle.problem.constellation, bundle.problem

    def compute(block):
        return evaluate(g, p, problem, _frames(block))

    def collect(block, result):
        n = block.b - block.a
        visit(block, np.asarray(result[0])[:n], np.asarray(result[1])[:n])

    bundle.chunks.blocks(compute, collect)


# ----------------------------------------------------------------------------- building


def rigid_directions(reference: np.ndarray) -> np.ndarray:
    """`(3m, 6)`: LED displacements of a small rigid motion ``[t, ω]`` (``t + ω × p``)."""
    m = reference.shape[0]
    a = np.zeros((m, 3, 6))
    a[:, :, :3] = np.eye(3)
    px, py, pz = reference.T
    z = np.zeros(m)
    # ω × p = −[p]× ω
    a[:, :, 3:] = -np.stack(
        [np.stack([z, -pz, py], -1), np.stack([pz, z, -px], -1), np.stack([-py, px, z], -1)], 1
    )
    return a.reshape(3 * m, 6)


def gauge_basis(reference: np.ndarray, seen: np.ndarray, probe: bool) -> np.ndarray:
    """`(3m, 3m)` basis of the constellation corrections: every coordinate of the seen
    LEDs with probe data, else an orthonormal basis free of rigid motion of the
    reference; unseen LEDs get no parameters (kept at the reference). Columns without
    a direction are zero (fixed shapes: one compilation per LED count)."""
    rows = np.repeat(seen, 3)
    basis = np.zeros((3 * reference.shape[0], 3 * reference.shape[0]))
    if probe:
        basis[:, : rows.sum()] = np.eye(3 * reference.shape[0])[:, rows]
        return basis
    u, _, _ = np.linalg.svd(rigid_directions(reference[seen]), full_matrices=True)
    basis[np.ix_(rows, np.arange(3 * int(seen.sum()) - 6))] = u[:, 6:]
    return basis


def chunk_size(n: int, chunk: int | None) -> int:
    if chunk is not None:
        return int(chunk)
    return 256 if n <= 4096 else 1024 if n <= 65536 else 2048


def tracker_frames(
    data: CalibrationData, weights: Weights, size: int, block: int | None = None
) -> TrackerFrames:
    """The frames of `data` as the kernels read them, in chunks of `size` frames and blocks
    of `BLOCK_FRAMES` (`block`) or fewer (a recording shorter than a block is one block of
    as many chunks as it needs)."""
    per = max(1, (_calib_frames.BLOCK_FRAMES if block is None else int(block)) // size)
    per = min(per, -(-data.n_frames // size))
    return TrackerFrames(
        positions=data.positions,
        columns=data.columns,
        frame=data.frame,
        time=data.time,
        drift=data.drift,
        direction=data.direction,
        moving=data.moving,
        weights=weights,
        size=size,
        per=per,
    )


def whole(frames: TrackerFrames) -> Frames:
    """All frames at once, `(frames, ...)` (padding of weight zero included): for the
    pure residual function on small recordings."""
    parts = [frames.block(i).frames for i in range(frames.n_blocks)]
    return Frames(
        **{
            k: jnp.asarray(np.concatenate([b[k].reshape(-1, *b[k].shape[2:]) for b in parts]))
            for k in parts[0]
        }
    )


#: assumed probe uncertainty: position [m], rotation [rad]
PROBE_SIGMA = (20e-6, 2e-4)


class ProbeObservations(eqx.Module):
    """6-DOF tool poses measured at `frames.time` (tracker clock): camera←tool
    `probed` `(n, 7)` ``wxyz_xyz``, weighted by `PROBE_SIGMA`."""

    frames: Frames
    probed: Float[Array, "n 7"]


def probe_observations(probe, data: CalibrationData, tau: float) -> ProbeObservations | None:
    """The recording's `/probe` poses inside the robot log's time span (None without)."""
    if probe is None or probe.time.shape[0] == 0:
        return None
    t = np.asarray(probe.time, float)
    inside = (t + tau >= data.log_time[0]) & (t + tau <= data.log_time[-1])
    if not inside.any():
        return None
    t = t[inside]
    frames = Frames(
        time=jnp.asarray(t),
        direction=jnp.asarray(motion_direction(data.log_time, data.joints, t + tau)),
        moving=jnp.asarray(motion_sign(data.log_time, data.joints, t + tau, data.motion_threshold)),
        drift=jnp.asarray(np.interp(t, data.time, data.drift)),
        measured=jnp.zeros((t.size, 0, 3)),
        sqrt_weight=jnp.zeros((t.size, 0)),
        base_from_flange=jnp.zeros((t.size, 7)),
    )
    probed = np.concatenate(
        [probe.tool_pose.quaternion_wxyz[inside], probe.tool_pose.position[inside]], -1
    )
    return ProbeObservations(frames, jnp.asarray(probed))


def probe_residual(
    g: Array, problem: BundleProblem, frames: Frames, probed: Float[Array, "n 7"]
) -> Float[Array, "n 6"]:
    """The 6-DOF residual `(n, 6)` of camera←tool poses `probed` (``wxyz_xyz``) measured
    at `frames`: `probe_pose_error` of the model's tool pose (the tracker's scale applied
    to its position)."""
    tool, eff = tool_poses(g, problem, frames)
    return probe_pose_error(
        tool.rotation().wxyz, (1.0 + eff.tracker_scale) * tool.translation(), probed
    )


def probe_jacobian(
    g: Array, problem: BundleProblem, frames: Frames, probed: Float[Array, "n 7"]
) -> tuple[Float[Array, "n 6"], Float[Array, "n 6 q"]]:
    """`probe_residual` and its Jacobian in g `(n, 6, q)`: the residual's derivative in
    the tool pose's tangent (6 forward-mode tangents, every pose at once) times the
    tool's closed-form Jacobian (`_tool_jacobian`), and the tracker scale's column."""
    tool0, j_tool = _tool_jacobian(g, problem, frames)
    _, _, eff = _split(g, problem)

    def err(xi, scale):
        t = jaxlie.SE3(
            jax.vmap(lambda a, b: (jaxlie.SE3(a) @ jaxlie.SE3.exp(b)).wxyz_xyz)(tool0.wxyz_xyz, xi)
        )
        return probe_pose_error(t.rotation().wxyz, (1.0 + scale) * t.translation(), probed)

    xi0 = jnp.zeros((probed.shape[0], 6), g.dtype)
    scale = eff.tracker_scale
    r = err(xi0, scale)
    j_xi = jax.vmap(
        lambda dx: jax.jvp(lambda e: err(e, scale), (xi0,), (jnp.broadcast_to(dx, xi0.shape),))[1],
        out_axes=-1,
    )(jnp.eye(6, dtype=g.dtype))  # (n, 6, 6)
    j = jnp.einsum("nrk,nkq->nrq", j_xi, j_tool)
    at = _effect_index(problem, "tracker_scale")
    if at is not None and at < g.shape[0]:
        d_scale = jax.jvp(lambda s: err(xi0, s), (scale,), (jnp.ones_like(scale),))[1]
        j = j.at[..., at].set(d_scale)
    return r, j


def _effect_index(problem: BundleProblem, name: str) -> int | None:
    """The first entry of effect `name` in g (None where it is not in the problem)."""
    i = 12
    for n, size in zip(problem.free, effect_sizes(problem.effects, problem.free)):
        if n == name:
            return i
        i += size
    return None


def _probe_terms(g, problem: BundleProblem, obs: ProbeObservations):
    """Normal equations of the probe poses' residuals (`probe_jacobian`), weighted by
    `PROBE_SIGMA` (forward kinematics re-run: the probe times are not tracker frames):
    the totals and each pose's (`normal_terms`, a group per pose)."""
    kin = dataclasses.replace(problem, kinematic=True)
    r, j = probe_jacobian(g, kin, obs.frames, obs.probed)
    sigma = jnp.asarray(np.repeat(PROBE_SIGMA, 3), r.dtype)
    each = jnp.arange(r.shape[0], dtype=jnp.int32)[:, None]
    h, b, c = normal_terms(
        r, j, jnp.broadcast_to(1.0 / sigma, r.shape), (0, 0), None, None, 0, each
    )
    return h.sum(0), b.sum(0), c.sum(), (h, b)


class BundleData(eqx.Module):
    """What the normal equations of a bundle problem read besides θ: the problem at its
    current values, the tracker frames (`TrackerFrames`, read block by block), the
    constellation basis, the optional probe poses and the Gaussian prior of the
    estimated terms that carry one (on θ entries of g; none: `no_prior()`)."""

    problem: BundleProblem
    chunks: TrackerFrames | None = eqx.field(static=True)
    basis: Float[Array, "leds3 c"]
    probe: ProbeObservations | None
    prior: GaussianPrior = eqx.field(default_factory=no_prior)

    def with_frames(self, frames: TrackerFrames | None) -> BundleData:
        return dataclasses.replace(self, chunks=frames)


def prior_values(g: Array, data: BundleData) -> Array:
    """The values of the prior's entries at g: the effects' current values plus their
    corrections."""
    pr = data.problem
    current = [jnp.ravel(pr.effects.get(n)) for n in pr.free]
    if not current or data.prior.size == 0:
        return jnp.zeros(0, g.dtype)
    values = jnp.concatenate(current) + g[12:]
    return values[data.prior.index - 12]


def with_prior(h, b, cost, g, data: BundleData):
    """The normal equations with the prior added (`GaussianPrior.add_to`) on the g block
    of θ."""
    return data.prior.add_to(h, b, cost, prior_values(g, data))


def split_theta(theta: Array, data: BundleData) -> tuple[Array, Array]:
    """θ = [global (q), constellation coefficients (c)] → (g, LED positions `(m, 3)`)."""
    c = data.basis.shape[1]
    q = theta.shape[0] - c
    p = data.problem.constellation + (data.basis @ theta[q:]).reshape(-1, 3)
    return theta[:q], p


@composed
def bundle_normal(theta: Array, data: BundleData):
    """``(H, b, cost)`` of the bundle problem in θ (`robtraj.estimate._solve`): LED
    observations accumulated over the frames, block by block, plus the probe poses, plus
    the prior of the estimated terms that carry one (`with_prior`)."""
    g, p = _split_theta(theta, data.with_frames(None))
    terms = normal_equations(g, p, data.problem, data.chunks)
    return _normal_in_theta(g, data.with_frames(None), terms)


@eqx.filter_jit
def _split_theta(theta, data: BundleData):
    return split_theta(theta, data)


@eqx.filter_jit
def _normal_in_theta(g, data: BundleData, terms):
    return with_prior(*_in_theta(g, data, terms)[:3], g, data)


def bundle_normal_clustered(theta: Array, data: BundleData, cluster: np.ndarray, n_clusters: int):
    """`bundle_normal`, and the normal matrix `(G, P, P)` and score ``b`` `(G, P)` of each
    cluster of frames in θ (`cluster` as in `normal_equations_clustered`; each probe pose
    is a cluster of its own, after them): the input of `robust_covariance` (the prior is
    in the whole problem's, no cluster's)."""
    g, p = _split_theta(theta, data.with_frames(None))
    terms, per = normal_equations_clustered(g, p, data.problem, data.chunks, cluster, n_clusters)
    return _clustered_in_theta(g, data.with_frames(None), terms, per, n_clusters)


@eqx.filter_jit
def _clustered_in_theta(g, data: BundleData, terms, per, n_clusters: int):
    hgg, hgp, hpp, cg, cp_ = per
    h, b, c, probe = _in_theta(g, data, terms)
    h, b, c = with_prior(h, b, c, g, data)
    hs = jax.vmap(h_in_theta, in_axes=(0, 0, 0, None))(hgg, hgp, hpp, data.basis)
    scores = jnp.concatenate([cg, cp_.reshape(n_clusters, -1) @ data.basis], -1)
    if probe is not None:
        h2, b2 = probe
        nc = data.basis.shape[1]
        hs = jnp.concatenate([hs, jnp.pad(h2, ((0, 0), (0, nc), (0, nc)))])
        scores = jnp.concatenate([scores, jnp.pad(b2, ((0, 0), (0, nc)))])
    return h, b, c, hs, scores


def _in_theta(g, data: BundleData, terms):
    """The accumulated ``[g, vec(p)]`` terms (plus the probe poses) in θ coordinates."""
    hgg, hgp, hpp, bg, bp, c = terms
    probe = None
    if data.probe is not None:
        h2, b2, c2, probe = _probe_terms(g, data.problem, data.probe)
        hgg, bg, c = hgg + h2, bg + b2, c + c2
    b = jnp.concatenate([bg, data.basis.T @ bp.reshape(-1)])
    return h_in_theta(hgg, hgp, hpp, data.basis), b, c, probe


def h_in_theta(hgg, hgp, hpp, basis: Array) -> Array:
    """The normal matrix in θ = [g, constellation coefficients] from its ``[g, vec(p)]``
    blocks (symmetrised)."""
    q, m = hgg.shape[0], hpp.shape[0]
    basis3 = basis.reshape(m, 3, -1)
    hgp_b = hgp.reshape(q, 3 * m) @ basis
    hpp_b = jnp.einsum("mac,mab,mbd->cd", basis3, hpp, basis3)
    h = jnp.block([[hgg, hgp_b], [hgp_b.T, hpp_b]])
    return 0.5 * (h + h.T)


@eqx.filter_jit
def recentre(problem: BundleProblem, theta: Array, basis: Array) -> BundleProblem:
    """Absorb a θ step into the problem's current values (θ = 0 is then the estimate)."""
    d = theta
    q = d.shape[0] - basis.shape[1]
    cfb = jaxlie.SE3(problem.camera_from_base) @ jaxlie.SE3.exp(d[:6])
    fft = jaxlie.SE3(problem.flange_from_tool) @ jaxlie.SE3.exp(d[6:12])
    eff = apply_effects(problem.effects, problem.free, d[12:q])
    p = problem.constellation + (basis @ d[q:]).reshape(-1, 3)
    return eqx.tree_at(
        lambda pr: (pr.camera_from_base, pr.flange_from_tool, pr.effects, pr.constellation),
        problem,
        (cfb.wxyz_xyz, fft.wxyz_xyz, eff, p),
    )


def residuals(theta: Array, data: BundleData) -> Float[Array, " r"]:
    """Weighted LED residuals ``sqrt(w)·(measured − predicted)`` `(frames·leds·3,)` [m·√w]
    at θ, all frames at once: the pure function whose chunk-accumulated normal equations
    `bundle_normal` computes (``H = JᵀJ``, ``b = −Jᵀr`` with J the Jacobian of this)."""
    g, p = split_theta(theta, data)
    with jax.ensure_compile_time_eval():  # the frames are read, not traced
        frames = whole(data.chunks)
    pred = predict(g, p, data.problem, frames)
    return (frames.sqrt_weight[..., None] * (frames.measured - pred)).reshape(-1)
