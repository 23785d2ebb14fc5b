"""Recording → per-frame tool poses with per-frame quality (DESIGN 5.3)."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .._errors import UserError
from .._progress import progress_bar
from ..jax_ops import (
    led_variance,
    led_variances,
    matrix_to_quat,
    quat_conjugate,
    quat_multiply,
    rotation_angle,
    weighted_procrustes,
)
from ..recording import Recording, finite_points
from ._noise import noise_and_variance
from ._registration import Registration, _quat_matrix, register_leds
from ._static import static_segments
from ._weighting import LedFeatures, get_weighting, weighting_needs

CHUNK = 65536  # frames per kernel call: bounded memory on whole recordings


@dataclasses.dataclass(frozen=True)
class PoseEstimate:
    """Tool poses in the camera frame per tracker frame (camera←tool).

    `position` `(N, 3)` [m], `quaternion_wxyz` `(N, 4)`; NaN where `valid` is False
    (fewer than three usable LEDs or degenerate geometry). `rms` `(N,)` [m] weighted
    residual RMS; `n_used` `(N,)` LEDs used. `constellation` `(M, 3)` [m] in the tool
    frame, as used; `registration` when it came from the data.
    """

    time: np.ndarray
    position: np.ndarray
    quaternion_wxyz: np.ndarray
    rms: np.ndarray
    n_used: np.ndarray
    valid: np.ndarray
    led_ids: np.ndarray
    constellation: np.ndarray
    constellation_source: str
    registration: Registration | None
    weighting: str
    window: int
    notes: tuple[str, ...] = ()


def default_window(time: np.ndarray) -> int:
    """Odd number of frames spanning about 0.1 s (at least 5)."""
    dt = float(np.median(np.diff(time))) if time.size > 1 else 1.0
    n = max(5, int(round(0.1 / dt)))
    return n + (n % 2 == 0)


def _chunk_length(n: int, chunk: int) -> int:
    """Frames per kernel call: `chunk`, or for shorter recordings the next power of two
    (at least 4096), so the kernels are compiled for a few shapes only."""
    if n >= chunk:
        return chunk
    return min(chunk, max(4096, 1 << (n - 1).bit_length()))


def _slab(arr: np.ndarray, start: int, size: int, halo: int, fill) -> np.ndarray:
    """``arr[start - halo : start + size + halo]`` with `fill` beyond the ends: always
    ``size + 2·halo`` frames, so every chunk has the same shape."""
    lo, hi = start - halo, start + size + halo
    out = np.full((hi - lo, *arr.shape[1:]), fill, arr.dtype)
    s, e = max(lo, 0), min(hi, arr.shape[0])
    out[s - lo : e - lo] = arr[s:e]
    return out


def _over_chunks(n: int, size: int, prepare: Callable, compute: Callable, collect: Callable):
    """Run a kernel over the chunks ``[a, a + size)`` of n frames as a pipeline.

    `prepare(a)` (slicing, padding, host-to-device copy) runs on a worker thread one
    chunk ahead; `compute(*args)` is dispatched asynchronously, and the previous chunk's
    result is fetched by `collect(a, result)` while the device works on the next one.
    """
    starts = list(range(0, n, size))
    with ThreadPoolExecutor(max_workers=1) as pool:
        ahead = pool.submit(prepare, starts[0])
        pending = None
        for i, a in enumerate(starts):
            args = ahead.result()
            if i + 1 < len(starts):
                ahead = pool.submit(prepare, starts[i + 1])
            result = compute(*args)
            if pending is not None:
                collect(*pending)
            pending = (a, result)
        collect(*pending)


@functools.partial(jax.jit, static_argnames=("window", "variants"))
def _variance_chunk(x: jax.Array, window: int, variants: tuple[str, ...]) -> jax.Array:
    h = window // 2
    return jnp.stack(led_variances(x, window, variants=variants))[:, h : x.shape[0] - h]


def chunked_led_variance(
    positions: np.ndarray, window: int, variant: str, chunk: int = CHUNK
) -> np.ndarray:
    """`led_variance` over a whole recording in chunks with a halo of half a window."""
    (out,) = chunked_led_variances(positions, window, (variant,), chunk)
    return out


def chunked_led_variances(
    positions: np.ndarray, window: int, variants: tuple[str, ...], chunk: int = CHUNK
) -> tuple[np.ndarray, ...]:
    """`led_variances` (several variants, one pass) over a whole recording in chunks."""
    n = positions.shape[0]
    h = window // 2
    size = _chunk_length(n, chunk)
    out = np.empty((len(variants), *positions.shape[:2]))

    def prepare(a):
        return (jax.device_put(_slab(positions, a, size, h, np.nan)),)

    def collect(a, v):
        b = min(n, a + size)
        out[:, a:b] = np.asarray(v)[:, : b - a]

    _over_chunks(n, size, prepare, lambda x: _variance_chunk(x, window, variants), collect)
    return tuple(out)


def led_emission_angles(position, quaternion_wxyz, constellation, normals):
    """Emission angle [rad] `(frames, leds)` of each LED toward the camera at the origin of
    the camera frame, from tool poses and the constellation/normals in the tool frame."""
    return np.asarray(
        _emission_angles(
            np.asarray(position),
            np.nan_to_num(quaternion_wxyz),
            np.asarray(constellation, np.float64),
            np.asarray(normals, np.float64),
        )
    )


@jax.jit
def _emission_angles(position, quaternion_wxyz, constellation, normals):
    # component by component, `(frames, leds)` each: XLA fuses it into one loop, where
    # reductions over axes of length 3 are slow on CPU
    r = jax.vmap(lambda q: jaxlie.SO3(q).as_matrix())(quaternion_wxyz)

    def rotate(v):
        return [sum(r[:, i, c, None] * v[None, :, c] for c in range(3)) for i in range(3)]

    p = rotate(constellation)
    # the LED's direction to the camera (unnormalised: atan2 of the cross and dot
    # products needs no unit length) and its normal
    x, y, z = (-(p[i] + position[:, i, None]) for i in range(3))
    u, v, w = rotate(normals)
    cross = jnp.sqrt((y * w - z * v) ** 2 + (z * u - x * w) ** 2 + (x * v - y * u) ** 2)
    return jnp.arctan2(cross, x * u + y * v + z * w)


def _select(rec: Recording, leds, reference_leds):
    """LED ids, positions `(N, K, 3)`, nominal constellation and normals `(K, 3)` (or
    None) and reference LED ids for the LEDs of the rigid body."""
    tool = rec.tool
    all_ids = np.asarray(rec.led_ids)
    if leds is None:
        leds = tool.led_ids if tool is not None else all_ids
    leds = np.asarray(leds)
    missing = leds[~np.isin(leds, all_ids)]
    if missing.size:
        raise UserError(f"LEDs {missing.tolist()} are not in the recording")
    cols = np.array([np.flatnonzero(all_ids == i)[0] for i in leds])
    if np.array_equal(cols, np.arange(all_ids.size)):
        positions = np.asarray(rec.positions, np.float64)
    else:
        positions = np.asarray(rec.positions[:, cols], np.float64)
    nominal = normals = None
    if tool is not None and tool.constellation is not None:
        tool_ids = np.asarray(tool.led_ids)
        have = np.isin(leds, tool_ids)
        rows = np.array([np.flatnonzero(tool_ids == i)[0] if h else 0 for i, h in zip(leds, have)])
        nominal = np.where(have[:, None], np.asarray(tool.constellation)[rows], np.nan)
        if tool.normals is not None:
            normals = np.where(have[:, None], np.asarray(tool.normals)[rows], np.nan)
    if reference_leds is None and tool is not None:
        reference_leds = tool.reference_leds
    reference = None if reference_leds is None else np.asarray(reference_leds)
    return leds, positions, nominal, normals, reference


def fit_poses(
    constellation: np.ndarray,
    positions: np.ndarray,
    weights: np.ndarray,
    chunk: int = CHUNK,
    advance: Callable = lambda n=1: None,
):
    """Weighted Procrustes over all frames in chunks → numpy arrays of a RigidFit."""
    n = positions.shape[0]
    size = _chunk_length(n, chunk)
    model = jnp.asarray(constellation)
    parts = []

    def prepare(a):
        return (
            jax.device_put(_slab(positions, a, size, 0, np.nan)),
            jax.device_put(_slab(np.asarray(weights, np.float64), a, size, 0, 0.0)),
        )

    def collect(a, fit):
        b = min(n, a + size)
        parts.append(jax.tree.map(lambda v: np.asarray(v)[: b - a], fit))
        advance(b - a)

    _over_chunks(n, size, prepare, lambda x, w: weighted_procrustes(model, x, w), collect)
    return jax.tree.map(lambda *x: np.concatenate(x), *parts)


@functools.partial(jax.jit, static_argnames=("weighting", "params", "window"))
def _poses_chunk(model, x_halo, usable, variance, pairwise, *, weighting, params, window):
    """Pairwise variance (if the scheme needs it and `pairwise` is None), weights and
    poses of one chunk.

    `x_halo` holds the chunk's positions with half a window on each side; `variance`
    the paper variance of the chunk's frames (NaN where the scheme does not need it).
    """
    h = window // 2
    x = x_halo[h : x_halo.shape[0] - h]
    seen = jnp.all(jnp.isfinite(x), axis=-1) & usable[None]
    if pairwise is None:
        if "pairwise_variance" in weighting_needs(weighting):
            pairwise = led_variance(x_halo, window, variant="pairwise")[h : x_halo.shape[0] - h]
        else:
            pairwise = jnp.full(seen.shape, jnp.nan, x.dtype)
    features = LedFeatures(
        visible=seen,
        variance=variance,
        pairwise_variance=pairwise,
        residual=jnp.zeros(seen.shape, x.dtype),
        emission_angle=jnp.full(seen.shape, jnp.nan, x.dtype),
        noise_variance=jnp.full(seen.shape, jnp.nan, x.dtype),
    )
    weights = get_weighting(weighting)(features, **dict(params))
    return weighted_procrustes(model, x, weights)


def fused_poses(
    constellation: np.ndarray,
    positions: np.ndarray,
    usable: np.ndarray,
    variance: np.ndarray | None,
    weighting: str,
    params: dict,
    window: int,
    chunk: int = CHUNK,
    advance: Callable = lambda n=1: None,
    pairwise: np.ndarray | None = None,
):
    """Poses of a whole recording for a scheme that needs no previous fit, as one
    jit-compiled kernel per chunk (pairwise variance unless given, weights, Procrustes)
    run as a pipeline over the chunks → numpy arrays of a RigidFit."""
    n = positions.shape[0]
    h = window // 2
    size = _chunk_length(n, chunk)
    model = jnp.asarray(constellation)
    usable_j = jnp.asarray(usable)
    var = np.full(positions.shape[:2], np.nan) if variance is None else variance
    parts = []

    def prepare(a):
        return (
            jax.device_put(_slab(positions, a, size, h, np.nan)),
            jax.device_put(_slab(var, a, size, 0, np.nan)),
            None if pairwise is None else jax.device_put(_slab(pairwise, a, size, 0, np.nan)),
        )

    def compute(x, v, pw):
        return _poses_chunk(
            model,
            x,
            usable_j,
            v,
            pw,
            weighting=weighting,
            params=tuple(sorted(params.items())),
            window=window,
        )

    def collect(a, fit):
        b = min(n, a + size)
        parts.append(jax.tree.map(lambda v: np.asarray(v)[: b - a], fit))
        advance(b - a)

    _over_chunks(n, size, prepare, compute, collect)
    return jax.tree.map(lambda *x: np.concatenate(x), *parts)


def residuals(fit, constellation: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Distance [m] of each seen LED from the fitted pose, `(N, M)` (NaN unseen)."""
    r = _quat_matrix(np.nan_to_num(fit.quaternion_wxyz))
    pred = np.einsum("fij,mj->fmi", r, constellation) + np.nan_to_num(fit.position)[:, None, :]
    return np.linalg.norm(positions - pred, axis=-1)


def estimate_poses(
    rec: Recording,
    *,
    weighting: str = "led_noise",
    window: int | None = None,
    constellation: np.ndarray | None = None,
    register: bool = True,
    params: dict | None = None,
    progress: bool | None = None,
    leds: list[int] | np.ndarray | None = None,
    reference_leds: list[int] | np.ndarray | None = None,
    segments: list[tuple[int, int]] | str | None = None,
) -> PoseEstimate:
    """Per-frame camera←tool poses of a whole recording.

    The constellation is, in order of preference: `constellation` if given; the one
    registered from the data's static segments (`register=True`, needs reference LEDs);
    the nominal `/tool/constellation`. LEDs that registration cannot reference fall back
    to their nominal position when there is one, else they are not used.

    `leds` restricts the fit to those LED ids (the rigid body; default: the tool's LEDs,
    else all); `reference_leds` overrides the tool's; `segments` gives the frame ranges
    registration may use (``"all"``: every frame, for a rigid body that never rests;
    default: the detected static segments).
    """
    scheme = get_weighting(weighting)
    needs = weighting_needs(weighting)
    params = params or {}
    ids, positions, nominal, normals, reference = _select(rec, leds, reference_leds)
    n, m = positions.shape[:2]
    if n < 2:
        raise UserError("the recording has fewer than two frames")
    seen = finite_points(positions)
    if seen.sum(1).max(initial=0) < 3:
        raise UserError("no frame has three or more LEDs seen: no pose can be computed")
    window = default_window(rec.time) if window is None else int(window)
    if window < 3 or window > n:
        raise UserError(f"--window must be between 3 and the number of frames ({n}), got {window}")
    notes = []
    iterative = bool(needs & {"residual", "emission_angle", "noise_variance"})
    registering = constellation is None and register and reference is not None
    # every variance the scheme and registration need, in one pass over the pair distances
    variants = (("paper",) if registering or "variance" in needs else ()) + (
        ("pairwise",) if "pairwise_variance" in needs else ()
    )
    with progress_bar("LED variance", n, progress) as advance:
        found = dict(
            zip(variants, chunked_led_variances(positions, window, variants) if variants else ())
        )
        advance(n)
    variance, pairwise = found.get("paper"), found.get("pairwise")

    registration = None
    if constellation is not None:
        const, source = np.asarray(constellation, np.float64), "given"
    else:
        const, source = None, "nominal"
        if registering:
            if segments is None:
                segments = static_segments(rec.time, positions)
            elif segments == "all":
                segments = [(0, n)]
            try:
                registration = register_leds(positions, variance, segments, ids, reference, nominal)
            except UserError as e:
                if nominal is None:
                    raise
                notes.append(f"registration not possible ({e}); nominal constellation used")
        if registration is not None:
            const, source = registration.positions.copy(), "registered"
            lost = ~registration.referenced
            if lost.any() and nominal is not None:
                const[lost] = nominal[lost]
                notes.append(
                    f"LEDs {ids[lost].tolist()} not registered "
                    f"({'; '.join(sorted(set(registration.reasons.values())))}): nominal positions used"
                )
        elif nominal is not None:
            const = np.asarray(nominal, np.float64)
        else:
            raise UserError(
                "no constellation: the recording has no /tool, none was given, and "
                "registration needs three reference LEDs"
            )
    usable = np.isfinite(const).all(1)
    const0 = np.where(usable[:, None], const, 0.0)
    if not iterative:
        with progress_bar("poses", n, progress) as advance:
            fit = fused_poses(
                const0,
                positions,
                usable,
                variance,
                weighting,
                params,
                window,
                advance=advance,
                pairwise=pairwise,
            )
        return _estimate(rec, fit, ids, const, source, registration, weighting, window, notes)
    seen_used = seen & usable[None]
    if variance is None:
        variance = np.full((n, m), np.nan)
    if pairwise is None:
        pairwise = np.full((n, m), np.nan)
    features = LedFeatures(
        visible=jnp.asarray(seen_used),
        variance=jnp.asarray(variance),
        pairwise_variance=jnp.asarray(pairwise),
        residual=jnp.zeros((n, m)),
        emission_angle=jnp.full((n, m), jnp.nan),
        noise_variance=jnp.full((n, m), jnp.nan),
    )
    with progress_bar("poses", n * 3, progress) as advance:
        # features from a previous fit: start uniform, refine twice
        fit = fit_poses(const0, positions, np.asarray(seen_used, np.float64), advance=advance)
        for it in range(2):
            angles = None
            want = "emission_angle" in needs or ("noise_variance" in needs and it == 0)
            if normals is not None and want:
                angles = led_emission_angles(fit.position, fit.quaternion_wxyz, const0, normals)
                angles = np.where(seen_used & fit.valid[:, None], angles, np.nan)
            if "emission_angle" in needs:
                if angles is None:
                    raise UserError(
                        f"{weighting} weighting needs LED normals in /tool (emission angles)"
                    )
                features = dataclasses.replace(features, emission_angle=jnp.asarray(angles))
            if "noise_variance" in needs and it == 0:
                features = dataclasses.replace(
                    features,
                    noise_variance=jnp.asarray(noise_and_variance(positions, angles, ids)[1]),
                )
            if "residual" in needs:
                res = np.nan_to_num(residuals(fit, const0, positions))
                features = dataclasses.replace(features, residual=jnp.asarray(res))
            weights = np.asarray(scheme(features, **params))
            fit = fit_poses(const0, positions, weights, advance=advance)
    return _estimate(rec, fit, ids, const, source, registration, weighting, window, notes)


def _estimate(rec, fit, ids, const, source, registration, weighting, window, notes):
    return PoseEstimate(
        time=np.asarray(rec.time),
        position=fit.position,
        quaternion_wxyz=fit.quaternion_wxyz,
        rms=fit.rms,
        n_used=np.asarray(fit.n_used),
        valid=np.asarray(fit.valid, bool),
        led_ids=ids,
        constellation=const,
        constellation_source=source,
        registration=registration,
        weighting=weighting,
        window=window,
        notes=tuple(notes),
    )


def errors_against(
    est: PoseEstimate, position: np.ndarray, quaternion_wxyz: np.ndarray, *, gauge: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Position error [m] and single-angle orientation error [rad] of the estimated poses
    against reference camera←tool poses (e.g. `/truth/tool_pose`), NaN where not valid.

    With `gauge=True` the constant tool-frame offset between the estimate's tool frame
    (e.g. the reference-LED frame of a registration) and the reference's is fitted
    (mean relative pose over valid frames) and removed first.
    """
    v = est.valid
    r_ref = _quat_matrix(quaternion_wxyz)
    r_est = _quat_matrix(np.nan_to_num(est.quaternion_wxyz))
    # relative pose ref⁻¹·est in the tool frame
    rel_r = np.einsum("fji,fjk->fik", r_ref, r_est)
    rel_t = np.einsum("fji,fj->fi", r_ref, np.nan_to_num(est.position) - position)
    if gauge and v.any():
        u, _, vt = np.linalg.svd(rel_r[v].mean(0))
        g_r = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
        g_t = rel_t[v].mean(0)
    else:
        g_r, g_t = np.eye(3), np.zeros(3)
    pos_err = np.linalg.norm(rel_t - g_t, axis=-1)
    q_est = jnp.asarray(np.nan_to_num(est.quaternion_wxyz))
    q_g = jnp.broadcast_to(matrix_to_quat(jnp.asarray(g_r)), q_est.shape)
    ang = np.asarray(
        rotation_angle(jnp.asarray(quaternion_wxyz), quat_multiply(q_est, quat_conjugate(q_g)))
    )
    return np.where(v, pos_err, np.nan), np.where(v, ang, np.nan)
