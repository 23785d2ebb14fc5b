"""A recording prepared for the engine (`Setup`): the start of every bundle fit, score test
and prediction of `robtraj.estimate.calibration`.

`setup` reads as its steps: the effects in the problem (`_calib_parameters`), the
observations (`_calib_data`, with the noise model estimated on a background thread
meanwhile), the effects and poses to start from (`_calib_init`), the problem built for
the observations' shapes (`_calib_problem`) with the clusters of the robust covariance
(`_calib_clusters`), its kernels compiled on the compiling thread (`_compile_ahead`)
while the start is computed, then the weights, the start values and the normal
equations there.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._errors import UserError
from .._mappings import make_room
from ..model import Effects
from ..recording import Pose, Recording
from . import _calib_problem as cp
from ._calib_clusters import frame_clusters, padded_clusters, robust_affordable
from ._calib_data import CalibrationData, observation_weights, observations
from ._calib_frames import Weights
from ._calib_init import start_effects, start_poses
from ._calib_parameters import (
    droppable,
    effects_in_problem,
    has_column,
    in_model,
    readable_names,
    theta_names,
)
from ._calib_problem import BundleData, BundleProblem, bundle_normal
from ._compile_ahead import CompileAhead
from ._noise import NoiseModel
from ._prior import term_prior
from ._solve import compile_steps, normal_at


@dataclasses.dataclass(frozen=True)
class Setup:
    """A recording prepared for the engine: the observations (`data`), the problem at its
    start (`bundle`), parameter names and which ones may be dropped, the normal matrix
    at the start (`h0`; `normal0` the engine's ``(H, b, cost)`` there), the clusters of
    the robust covariance and the noise model behind the weights."""

    data: CalibrationData
    bundle: BundleData
    gauge: str
    initial: dict
    free: tuple[str, ...]  # effects in the problem: estimated ones and held ones
    estimated: tuple[str, ...]
    in_model: np.ndarray  # θ entries of the poses, the estimated effects, the constellation
    q: int
    w_user: Weights  # the fit's weights, computed per block of frames
    used: np.ndarray  # (frames, leds) bool: observations of non-zero weight
    names_theta: list[str]
    phi_names: list[str]
    droppable: np.ndarray
    has_column: np.ndarray  # θ entries that are parameters (not padding of the basis)
    h0: np.ndarray
    n_residuals: int
    normal0: tuple | None
    clusters: tuple[np.ndarray, int]  # cluster of every chunked frame, their count
    clustered: bool  # the cluster-robust covariance is computed (`ROBUST_MAX_GLOBAL`)
    noise: NoiseModel | None  # the recording's noise model where it gave the weights
    noise_info: dict[str, Any]
    ahead: CompileAhead  # the fit's later kernels, compiling on a background thread
    #: the result keeps the `(frames, leds)` arrays (residuals, weights)
    per_observation: bool = True


def setup(
    recording: Recording,
    estimate,
    init,
    weights,
    chunk,
    say: Callable[[str], None],
    normal: bool = True,
    space=(),
    motion=None,
    start_only: bool = False,
    solver=None,
    clustered: bool = False,
    per_observation: bool = True,
    block: int | None = None,
) -> Setup:
    """Observations, weights, start and problem of one fit. `weights` None: from the
    recording's noise model (uniform where it cannot be estimated) with `normal`, else
    uniform. `init`: the `CalibrationResult` to start from (its gauge reference and
    clock offset too). `start_only`: the normal equations are wanted at the start alone
    (no step is taken): LED-level effects at zero then take the rigid path even when
    free. With `normal`, the kernels of the fit (its normal equations; the steps of
    `solver`; the clustered pass with `clustered`) are compiled on a background thread
    while the weights and the start are computed (`_compile_ahead`). The frames are read
    in blocks of `block` frames (default `BLOCK_FRAMES`) whenever they are needed;
    `per_observation`: the fit's result keeps its `(frames, leds)` arrays."""
    free, estimated = effects_in_problem(estimate, space)
    obs = observations(recording, init, weights, motion, normal, say)
    effects0 = start_effects(obs.data, free, init)
    names, q = theta_names(effects0, free, obs.data.n_leds)
    clustered = clustered and robust_affordable(q, say)
    if cleared := make_room():
        say(cleared)
    # the problem's structure and its kernels, on the compiling thread meanwhile
    ahead = CompileAhead()
    structure = ahead.run(
        _structure,
        ahead,
        obs.data,
        effects0,
        (free, estimated, start_only),
        (q, len(names)),
        obs.start,
        (obs.probe, obs.time_offset),
        (chunk, block),
        solver if normal else None,
        normal,
        clustered,
    )
    # the start and the weights (while the noise model is estimated)
    z, x = start_poses(obs.data, effects0, init, say)
    w_user, noise, noise_info = observation_weights(obs)
    bundle, clusters, first = structure.result()
    data = obs.data
    del obs
    bundle = eqx.tree_at(
        lambda b: (b.problem.camera_from_base, b.problem.flange_from_tool),
        bundle,
        (jax.device_put(z), jax.device_put(x)),
    ).with_frames(bundle.chunks.replace(weights=w_user))
    ahead.wait(*first)
    normal0 = normal_at(bundle_normal, jnp.zeros(len(names)), bundle) if normal else None
    h0 = np.asarray(normal0[0]) if normal else np.zeros((0, 0))
    if not np.all(np.isfinite(h0)):
        raise UserError("the observations give non-finite normal equations at the start")
    probe, basis, used = bundle.probe, np.asarray(bundle.basis), _used(data, w_user)
    return Setup(
        data=data,
        bundle=bundle,
        gauge="probe" if probe is not None else "reference_constellation",
        initial={
            "camera_from_base": Pose.from_wxyz_xyz(z),
            "flange_from_tool": Pose.from_wxyz_xyz(x),
        },
        free=free,
        estimated=estimated,
        in_model=in_model(names, free, estimated, data.robot),
        q=q,
        w_user=w_user,
        used=used,
        names_theta=names,
        phi_names=readable_names(names, q, basis, data.led_ids),
        droppable=droppable(names, q),
        has_column=has_column(q, basis),
        n_residuals=3 * int(np.sum(used)) + (0 if probe is None else 6 * probe.probed.shape[0]),
        h0=h0,
        normal0=normal0,
        clusters=clusters,
        clustered=clustered,
        noise=noise,
        noise_info=noise_info,
        ahead=ahead,
        per_observation=per_observation,
    )


def _used(data: CalibrationData, w: Weights) -> np.ndarray:
    """`(frames, leds)` bool: the observations of non-zero weight. The noise model's
    variance is finite and positive wherever an LED is seen, so only the user's weights
    can leave out more than the unseen."""
    if w.user is None:
        return data.seen
    at = np.asarray(w.user, float)[data.frame][:, data.columns]
    return data.seen & np.isfinite(at) & (at > 0)


def _structure(
    ahead: CompileAhead,
    data: CalibrationData,
    effects0: Effects,
    names: tuple[tuple[str, ...], tuple[str, ...], bool],
    sizes: tuple[int, int],
    start: np.ndarray,
    probe_poses: tuple,
    sizes_read: tuple[int | None, int | None],
    solver,
    normal: bool,
    clustered: bool,
):
    """The bundle problem of `setup` at placeholder poses and uniform weights (its shapes
    and static parts are those of the fit; `probe_poses`: the recording's `/probe` and
    the clock offset), the clusters of the robust covariance and the compilations of the
    fit's kernels (queued on `ahead`, after this): returns ``(bundle, clusters, futures
    of the kernels the start and the solve need)``."""
    free, estimated, start_only = names
    q, p = sizes  # global parameters, all of θ
    probe = cp.probe_observations(probe_poses[0], data, probe_poses[1])
    basis = cp.gauge_basis(data.reference, data.led_seen, probe is not None)
    kinematic = any(cp.is_kinematic(n) for n in free) or any(
        cp.is_kinematic(n) for n in effects0.terms
    )
    identity = jax.device_put(np.array([1.0, 0, 0, 0, 0, 0, 0]))
    problem = BundleProblem(
        robot=data.robot,
        camera_from_base=identity,
        flange_from_tool=identity,
        constellation=jax.device_put(np.asarray(start, float)),
        normals=jax.device_put(data.normals),
        effects=effects0,
        log_time=jax.device_put(data.log_time),
        joints=jax.device_put(data.joints),
        free=free,
        kinematic=kinematic,
        # LED-level effects at zero move no LED: the rigid path serves while none is
        # estimated (a step would move them), or for the normal equations at the start
        rigid_leds=(start_only or not any(cp.is_led_level(n) for n in estimated))
        and all(
            float(np.max(np.abs(effects0.get(n)))) == 0.0
            for n in (*cp.LED_EFFECTS, *effects0.terms)
            if cp.is_led_level(n)
        ),
        led_columns=start_only,
    )
    chunk, block = sizes_read
    chunks = cp.tracker_frames(data, Weights(), cp.chunk_size(data.n_frames, chunk), block)
    if not kinematic:
        chunks = chunks.replace(base_from_flange=cp.flange_poses_of(problem, chunks))
    cluster = frame_clusters(data, chunks)
    blocks, at = [], 12
    for name in free:
        if name in estimated:
            blocks.append((name, at))
        at += int(np.size(effects0.get(name)))
    bundle = BundleData(
        problem=problem,
        chunks=chunks,
        basis=jax.device_put(basis),
        probe=probe,
        prior=term_prior(blocks),
    )
    first = []
    # the block kernels compile for a placeholder block of the fit's shapes
    g0, m = jnp.zeros(q), data.n_leds
    frames = _placeholder(chunks)
    if normal:
        acc, _ = cp.zero_terms(q, m)
        first.append(ahead.submit(cp.normal_block, g0, problem.constellation, problem, frames, acc))
    if solver is not None:
        first.append(compile_steps(ahead, solver, p))
        ahead.submit(cp.evaluate, g0, problem.constellation, problem, frames)
        if clustered:
            padded = padded_clusters(cluster[1])
            ids = jnp.zeros((chunks.per, chunks.size), jnp.int32)
            acc = cp.zero_terms(q, m, padded)
            ahead.submit(
                cp.normal_block_clustered, g0, problem.constellation, problem, frames, ids,
                padded, acc,
            )  # fmt: skip
    return bundle, cluster, first


def _placeholder(frames) -> cp.Frames:
    """Zeros of the shapes of a block of `frames` (kernels compile on these)."""
    k, c, m, j = frames.per, frames.size, frames.n_leds, frames.direction.shape[1]
    z = jnp.zeros
    return cp.Frames(
        time=z((k, c)),
        direction=z((k, c, j)),
        moving=z((k, c, j)),
        drift=z((k, c)),
        measured=z((k, c, m, 3)),
        sqrt_weight=z((k, c, m)),
        base_from_flange=z((k, c, 7)),
    )
