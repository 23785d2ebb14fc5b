"""Normal equations of 6-DOF pose observations, per group of poses, with the joint angle
error maps' block accumulated from their two active knots.

The residual of pose n is `(6,)` (position [m], rotation vector [rad]); its Jacobian has
dense columns for the rigid transforms and every effect but the maps (`(N, 6, P_d)`), and
a map column per knot. A map's knot k of joint j acts on pose n only through the joint's
angle, with the hat value ``φₖ(qₙⱼ)``, non-zero at two knots: its column is the joint's
turn column ``uₙⱼ = ∂rₙ/∂qⱼ`` times that value. So the map rows of ``JᵀWJ`` and ``JᵀWr``
are sums over the poses of ``φ·uᵀW(·)`` put at the two knots (segment sums), never a
`(N, 6, knots)` Jacobian.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jaxtyping import Array, Float, Int

from ..model import map_active


def map_index(joints: Float[Array, "n joints"], n_knots: int):
    """Active knots of every joint's map at the logged angles: indices into the map block
    (joint j's knots at ``j·n_knots + k``) `(N, joints, 2)` and hat values `(N, joints, 2)`."""
    idx, w = map_active(joints, n_knots)
    offset = jnp.arange(joints.shape[-1], dtype=idx.dtype)[:, None] * n_knots
    return idx + offset, w


def map_jvp(
    j: Float[Array, "n 6 pd"],
    offset: tuple[int, int],
    index: Int[Array, "n joints 2"],
    weight: Float[Array, "n joints 2"],
    delta: Float[Array, "g m"],
    group: Int[Array, " n"],
) -> Float[Array, "n 6"]:
    """``J_map(n)·δ`` with pose n's map correction ``δ = delta[group[n]]`` (a step per
    group of poses): the residual change it makes, from the pose's active knots."""
    turn = j[..., offset[0] : offset[1]]  # (N, 6, joints)
    d = delta[group[:, None, None], index]  # (N, joints, 2)
    return jnp.einsum("nkj,nj->nk", turn, jnp.sum(weight * d, -1))


def normal_terms(
    r: Float[Array, "n 6"],
    j: Float[Array, "n 6 pd"],
    sqrt_w: Float[Array, "n 6"],
    offset: tuple[int, int],
    index: Int[Array, "n joints 2"] | None,
    weight: Float[Array, "n joints 2"] | None,
    n_map: int,
    members: Int[Array, "g m"],
):
    """``(H, b, cost)`` per group of poses, `(G, P, P)`, `(G, P)`, `(G,)` with
    ``P = P_d + n_map``: ``H = JᵀWJ``, ``b = −JᵀWr`` (r = predicted − measured, J its
    Jacobian; the engine's convention) and ``cost = rᵀWr``.

    - `r`, `j`: the unweighted residual and its dense Jacobian; `sqrt_w` the weights' roots.
    - `offset`: the dense columns ``(start, stop)`` of the joint offsets, which are the
      joints' turn columns ``∂r/∂qⱼ``.
    - `index`, `weight`: the maps' active knots (`map_index`); `n_map`: the size of the
      map block (0: no maps, `index` and `weight` unused).
    - `members` `(G, M)`: the poses of each group, padded with N (`group_members`); a
      group's dense block is then one product over its own poses, not a masked product
      over all of them per group.
    """
    n = r.shape[0]
    n_groups = members.shape[0]
    rw = sqrt_w * r
    jw = sqrt_w[..., None] * j
    # each pose's group (the padding, index N, dropped)
    group = (
        jnp.zeros(n, members.dtype)
        .at[members]
        .set(
            jnp.broadcast_to(jnp.arange(n_groups, dtype=members.dtype)[:, None], members.shape),
            mode="drop",
        )
    )
    jg = jnp.concatenate([jw, jnp.zeros_like(jw[:1])])[members]  # (G, M, 6, P_d)
    rg = jnp.concatenate([rw, jnp.zeros_like(rw[:1])])[members]  # (G, M, 6)
    h_dd = jnp.einsum("gmkp,gmkq->gpq", jg, jg)
    b_d = -jnp.einsum("gmkp,gmk->gp", jg, rg)
    cost = jnp.einsum("gmk,gmk->g", rg, rg)
    if n_map == 0:
        return h_dd, b_d, cost
    pd = j.shape[-1]
    u = jw[..., offset[0] : offset[1]]  # (N, 6, joints): weighted turn columns
    seg = group[:, None, None] * n_map + index  # (N, joints, 2)
    b_m = jax.ops.segment_sum(
        (-weight * jnp.einsum("nkj,nk->nj", u, rw)[..., None]).reshape(-1),
        seg.reshape(-1),
        n_groups * n_map,
    ).reshape(n_groups, n_map)
    ud = jnp.einsum("nkj,nkp->njp", u, jw)  # (N, joints, P_d)
    h_md = jax.ops.segment_sum(
        (weight[..., None] * ud[:, :, None, :]).reshape(-1, pd),
        seg.reshape(-1),
        n_groups * n_map,
    ).reshape(n_groups, n_map, pd)
    uu = jnp.einsum("nkj,nki->nji", u, u)  # (N, joints, joints)
    vals = uu[:, :, None, :, None] * weight[:, :, :, None, None] * weight[:, None, None, :, :]
    pair = (
        group[:, None, None, None, None] * n_map * n_map
        + index[:, :, :, None, None] * n_map
        + index[:, None, None, :, :]
    )
    h_mm = jax.ops.segment_sum(
        vals.reshape(-1), pair.reshape(-1), n_groups * n_map * n_map
    ).reshape(n_groups, n_map, n_map)
    h = jnp.concatenate(
        [
            jnp.concatenate([h_dd, jnp.swapaxes(h_md, 1, 2)], 2),
            jnp.concatenate([h_md, h_mm], 2),
        ],
        1,
    )
    return h, jnp.concatenate([b_d, b_m], 1), cost


def group_members(label: np.ndarray) -> np.ndarray:
    """`(G, M)`: the indices of the poses of each group ``0 … G−1`` of `label` `(N,)`,
    padded with N to the largest group's size M."""
    label = np.asarray(label)
    n_groups = int(label.max()) + 1 if label.size else 1
    rows = [np.flatnonzero(label == g) for g in range(n_groups)]
    out = np.full((n_groups, max(len(x) for x in rows)), label.size, np.int32)
    for g, x in enumerate(rows):
        out[g, : len(x)] = x
    return out


def jacobian_rows(
    j: Float[np.ndarray, "n 6 pd"],
    sqrt_w: Float[np.ndarray, "n 6"],
    offset: tuple[int, int],
    index: Int[np.ndarray, "n joints 2"],
    weight: Float[np.ndarray, "n joints 2"],
    n_map: int,
    columns: np.ndarray,
) -> list[sp.csr_matrix]:
    """Per residual component (x, y, z, rx, ry, rz), the whitened Jacobian rows `(N, P)`
    of every pose as a sparse matrix, restricted to `columns` (indices into θ): the dense
    columns and, for the maps, each joint's turn column times the hat values at its two
    active knots (what `normal_terms` accumulates, here kept per pose)."""
    j, sqrt_w = np.asarray(j, float), np.asarray(sqrt_w, float)
    n, _, pd = j.shape
    idx = np.asarray(index).reshape(n, -1) + pd
    rows = np.repeat(np.arange(n), idx.shape[1])
    out = []
    for c in range(6):
        jc = j[:, c, :] * sqrt_w[:, c : c + 1]
        full = sp.hstack([sp.csr_matrix(jc), sp.csr_matrix((n, n_map))], format="csr")
        if n_map:
            turn = jc[:, offset[0] : offset[1]]
            val = (turn[:, :, None] * np.asarray(weight)).reshape(n, -1)
            full = full + sp.csr_matrix((val.ravel(), (rows, idx.ravel())), shape=full.shape)
        out.append(full[:, columns])
    return out
