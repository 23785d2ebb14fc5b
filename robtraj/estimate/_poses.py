"""Recording → per-frame tool poses with per-frame quality (DESIGN 5.3).

`estimate_poses` passes over the recording chunk by chunk (`_pose_passes`): its memory
is that of a chunk plus the per-frame results, whether the recording is in memory or
opened lazily from its file (`robtraj.open_recording`), by the same code.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .._errors import UserError
from .._progress import progress_bar, progress_status
from ..jax_ops import (
    RigidFit,
    matrix_to_quat,
    quat_conjugate,
    quat_multiply,
    rotation_angle,
    weighted_procrustes,
)
from ..recording import FrameArray, Recording, finite_points
from ._chunks import CHUNK, Columns, chunk_length, over_chunks, over_frames, slab
from ._pose_passes import PoseArrays, collect_fit, led_emission_angles, pose_pass, variance_chunk
from ._pose_statistics import noise_inputs, residual_scale
from ._registration import Registration, _quat_matrix, register_pieces
from ._static import static_segments
from ._static_pieces import static_pieces
from ._weighting import get_weighting, weighting_needs

# the names other modules import from here
_chunk_length, _slab, _over_chunks = chunk_length, slab, over_chunks
__all__ = [
    "CHUNK",
    "PoseEstimate",
    "chunked_led_variance",
    "chunked_led_variances",
    "default_window",
    "errors_against",
    "estimate_poses",
    "fit_poses",
    "led_emission_angles",
]


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


def chunked_led_variance(
    positions: FrameArray,
    window: int,
    variant: str,
    chunk: int = CHUNK,
    keep: np.ndarray | None = None,
) -> np.ndarray:
    """`led_variance` over a whole recording in chunks with a halo of half a window;
    `keep`: the LED columns to return (`(N, len(keep))`; computed with all LEDs, as the
    variants compare each LED with the others)."""
    (out,) = chunked_led_variances(positions, window, (variant,), chunk, keep)
    return out


def chunked_led_variances(
    positions: FrameArray,
    window: int,
    variants: tuple[str, ...],
    chunk: int = CHUNK,
    keep: np.ndarray | None = None,
) -> tuple[np.ndarray, ...]:
    """`led_variances` (several variants, one pass) over a whole recording in chunks, of
    the LED columns `keep` (all when None)."""
    n, m = positions.shape[:2]
    h = window // 2
    size = chunk_length(n, chunk)
    cols = np.arange(m) if keep is None else np.asarray(keep)
    out = np.empty((len(variants), n, cols.size))

    def prepare(a):
        return (jax.device_put(slab(positions, a, size, h, np.nan)),)

    def collect(a, v):
        b = min(n, a + size)
        v = np.asarray(v)[:, : b - a]
        out[:, a:b] = v if keep is None else v[..., cols]

    over_chunks(n, size, prepare, lambda x: variance_chunk(x, window, variants), collect)
    return tuple(out)


def _select(rec: Recording, leds, reference_leds):
    """LED ids, positions `(N, K, 3)` (a `Columns` view: read by frame ranges), nominal
    constellation and normals `(K, 3)` (or None) and reference LED ids for the LEDs of the
    rigid body."""
    tool = rec.tool
    all_ids = np.asarray(rec.led_ids)
    if leds is None:
        leds = tool.led_ids if tool is not None else all_ids
    leds = np.asarray(leds)
    missing = leds[~np.isin(leds, all_ids)]
    if missing.size:
        raise UserError(f"LEDs {missing.tolist()} are not in the recording")
    cols = np.array([np.flatnonzero(all_ids == i)[0] for i in leds], np.int64)
    positions = Columns(rec.positions, cols)
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
    positions: FrameArray,
    weights: np.ndarray,
    chunk: int = CHUNK,
    advance: Callable = lambda n=1: None,
):
    """Weighted Procrustes over all frames in chunks → numpy arrays of a RigidFit."""
    n = positions.shape[0]
    size = chunk_length(n, chunk)
    model = jnp.asarray(constellation)

    def prepare(a):
        return (
            jax.device_put(slab(positions, a, size, 0, np.nan)),
            jax.device_put(slab(np.asarray(weights, np.float64), a, size, 0, 0.0)),
        )

    fields = tuple(f.name for f in dataclasses.fields(RigidFit))  # in the pytree's order
    collect = collect_fit(n, size, advance, fields)
    over_chunks(n, size, prepare, lambda x, w: weighted_procrustes(model, x, w), collect)
    return collect.rigid_fit()


class _Scan:
    """Per chunk of frames (`__call__(a, x)`): the most LEDs seen in one frame, and which
    LEDs are seen at all `(M,)`."""

    def __init__(self, m: int, advance: Callable) -> None:
        self.most, self.ever_seen, self.advance = 0, np.zeros(m, bool), advance

    def __call__(self, a: int, x: np.ndarray) -> None:
        seen = finite_points(x)
        self.most = max(self.most, int(seen.sum(1).max(initial=0)))
        self.ever_seen |= seen.any(0)
        self.advance(x.shape[0])


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
    chunk: int = CHUNK,
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

    `rec` may be in memory or opened lazily (`robtraj.open_recording`): every pass over
    the frames reads them `chunk` frames at a time (with a halo for the LED variance's
    window), so memory is that of a chunk plus the per-frame results (~80 bytes a frame),
    whatever the recording's length.
    """
    get_weighting(weighting)
    needs = weighting_needs(weighting)
    params = params or {}
    ids, positions, nominal, normals, reference = _select(rec, leds, reference_leds)
    n = positions.shape[0]
    if n < 2:
        raise UserError("the recording has fewer than two frames")
    registering = constellation is None and register and reference is not None
    with progress_bar("poses: reading the LEDs", n, progress) as advance:
        scan = _Scan(positions.shape[1], advance)
        if registering and segments is None:  # static segments from the same pass
            segments = static_segments(rec.time, positions, visit=scan, chunk=chunk)
        else:
            over_frames(positions, scan, chunk)
    if scan.most < 3:
        raise UserError("no frame has three or more LEDs seen: no pose can be computed")
    window = default_window(rec.time) if window is None else int(window)
    if window < 3 or window > n:
        raise UserError(f"--window must be between 3 and the number of frames ({n}), got {window}")
    iterative = bool(needs & {"residual", "emission_angle", "noise_variance", "residual_scale"})
    if "emission_angle" in needs and normals is None:
        raise UserError(f"{weighting} weighting needs LED normals in /tool (emission angles)")

    const, source, registration, notes = _constellation(
        positions, ids, nominal, reference, scan.ever_seen, constellation, registering,
        segments, window, chunk, progress,
    )  # fmt: skip
    usable = np.isfinite(const).all(1)
    const0 = np.where(usable[:, None], const, 0.0)
    variants = tuple(
        v for v, f in (("paper", "variance"), ("pairwise", "pairwise_variance")) if f in needs
    )
    kw = dict(weighting=weighting, params=params, window=window, variants=variants, needs=needs)
    if not iterative:
        with progress_bar("poses", n, progress) as advance:
            fit = pose_pass(positions, const0, usable, chunk=chunk, advance=advance, **kw)
        return _estimate(rec, fit, ids, const, source, registration, weighting, window, notes)
    # features from a previous fit: start uniform, refine twice
    with progress_bar("poses: uniform start", n, progress) as advance:
        fit = pose_pass(positions, const0, usable, chunk=chunk, advance=advance)
    noise = None
    if "noise_variance" in needs:
        with progress_bar("poses: noise model", 2 * n, progress) as advance:
            noise = noise_inputs(positions, const0, usable, normals, fit, ids, chunk, advance)
    for it in range(2):
        if it and not needs & {"residual", "emission_angle", "residual_scale"}:
            break  # the features do not change: neither would the weights nor the poses
        scale = None
        if "residual_scale" in needs:
            with progress_bar("poses: residual scale", 2 * n, progress) as advance:
                scale = residual_scale(positions, const0, usable, fit, chunk, advance)
        with progress_bar(f"poses: pass {it + 1} of 2", n, progress) as advance:
            fit = pose_pass(
                positions, const0, usable, prev=fit, noise=noise, normals=normals, scale=scale,
                chunk=chunk, advance=advance, **kw,
            )  # fmt: skip
    return _estimate(rec, fit, ids, const, source, registration, weighting, window, notes)


def _constellation(
    positions, ids, nominal, reference, ever_seen, given, registering, segments, window,
    chunk, progress,
):  # fmt: skip
    """The constellation to fit, where it came from, the registration and notes."""
    notes: list[str] = []
    if given is not None:
        return np.asarray(given, np.float64), "given", None, notes
    registration = None
    if registering:
        if segments == "all":
            segments = [(0, positions.shape[0])]
        pieces = static_pieces(positions, segments, window, chunk)
        try:
            with progress_status("poses: registering the LEDs", progress) as say:
                registration = register_pieces(
                    pieces, segments, ids, reference, nominal, ever_seen, say=say
                )
        except UserError as e:
            if nominal is None:
                raise
            notes.append(f"registration not possible ({e}); nominal constellation used")
    if registration is not None:
        const = registration.positions.copy()
        lost = ~registration.referenced
        if lost.any() and nominal is not None:
            const[lost] = nominal[lost]
            notes.append(
                f"LEDs {ids[lost].tolist()} not registered "
                f"({'; '.join(sorted(set(registration.reasons.values())))}): nominal positions used"
            )
        return const, "registered", registration, notes
    if nominal is not None:
        return np.asarray(nominal, np.float64), "nominal", None, notes
    raise UserError(
        "no constellation: the recording has no /tool, none was given, and "
        "registration needs three reference LEDs"
    )


def _estimate(rec, fit: PoseArrays, ids, const, source, registration, weighting, window, notes):
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
    est: PoseEstimate,
    position: np.ndarray,
    quaternion_wxyz: np.ndarray,
    *,
    gauge: bool = True,
    chunk: int = CHUNK,
) -> tuple[np.ndarray, np.ndarray]:
    """Position error [m] and single-angle orientation error [rad] of the estimated poses
    against reference camera←tool poses (e.g. `/truth/tool_pose`), NaN where not valid.

    With `gauge=True` the constant tool-frame offset between the estimate's tool frame
    (e.g. the reference-LED frame of a registration) and the reference's is fitted
    (mean relative pose over valid frames) and removed first. Computed `chunk` frames at a
    time.
    """
    v = est.valid
    n = v.shape[0]
    chunks = [(a, min(n, a + chunk)) for a in range(0, n, chunk)]

    def relative(a, b):
        """Relative pose ref⁻¹·est in the tool frame of frames a..b-1."""
        r_ref = _quat_matrix(quaternion_wxyz[a:b])
        r_est = _quat_matrix(np.nan_to_num(est.quaternion_wxyz[a:b]))
        rel_r = np.einsum("fji,fjk->fik", r_ref, r_est)
        rel_t = np.einsum("fji,fj->fi", r_ref, np.nan_to_num(est.position[a:b]) - position[a:b])
        return rel_r, rel_t

    g_r, g_t = np.eye(3), np.zeros(3)
    if gauge and v.any():
        sum_r, sum_t = np.zeros((3, 3)), np.zeros(3)
        for a, b in chunks:
            rel_r, rel_t = relative(a, b)
            sum_r += rel_r[v[a:b]].sum(0)
            sum_t += rel_t[v[a:b]].sum(0)
        u, _, vt = np.linalg.svd(sum_r / v.sum())
        g_r = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
        g_t = sum_t / v.sum()
    q_g = matrix_to_quat(jnp.asarray(g_r))
    pos_err, ang = np.full(n, np.nan), np.full(n, np.nan)
    for a, b in chunks:
        _, rel_t = relative(a, b)
        pos_err[a:b] = np.linalg.norm(rel_t - g_t, axis=-1)
        q_est = jnp.asarray(np.nan_to_num(est.quaternion_wxyz[a:b]))
        q_rel = quat_multiply(q_est, quat_conjugate(jnp.broadcast_to(q_g, q_est.shape)))
        ang[a:b] = np.asarray(rotation_angle(jnp.asarray(quaternion_wxyz[a:b]), q_rel))
    return np.where(v, pos_err, np.nan), np.where(v, ang, np.nan)
