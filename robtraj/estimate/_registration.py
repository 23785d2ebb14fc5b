"""Automated LED registration (paper section 3, DESIGN 5.2).

The tool frame is fixed by the three reference LEDs. With a nominal constellation it
is the nominal tool frame fitted to them (reference-LED frame plus the nominal TCP);
without one it is built from them alone: origin at the first, x toward the second, z
normal to their plane. Then, static segment by static segment, every LED seen together
with at least three referenced LEDs gets a tool-frame position from the
lowest-variance frames, until no more LEDs can be referenced. A second pass
re-estimates every LED with poses from all referenced LEDs.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from .._errors import UserError
from ..jax_ops import rotation_rows, weighted_procrustes

# frames per Procrustes call: every segment is fitted by the same compiled kernel
_BLOCK = 4096


@dataclasses.dataclass(frozen=True)
class Registration:
    """Registered constellation in the tool frame [m].

    `positions` `(M, 3)` NaN for LEDs that could not be referenced; `uncertainty` `(M,)`
    [m] standard error of each position (per axis, RMS over axes); `n_frames` `(M,)`
    frames that contributed; `reasons` maps unreferenced LED ids to why; `gauge` says
    how the tool frame was fixed.
    """

    led_ids: np.ndarray
    positions: np.ndarray
    uncertainty: np.ndarray
    n_frames: np.ndarray
    reasons: dict[int, str]
    gauge: str

    @property
    def referenced(self) -> np.ndarray:
        return np.all(np.isfinite(self.positions), axis=-1)


def _frames_from_three(p: np.ndarray) -> np.ndarray:
    """Coordinates of three points `(F, 3, 3)` in the frame they span (origin p0, x → p1,
    z normal to their plane), per frame."""
    x = p[:, 1] - p[:, 0]
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    z = np.cross(x, p[:, 2] - p[:, 0])
    zn = np.linalg.norm(z, axis=-1, keepdims=True)
    if np.any(zn < 1e-9):
        raise UserError("the three reference LEDs are collinear")
    z /= zn
    r = np.stack([x, np.cross(z, x), z], axis=1)  # rows: axes
    return np.einsum("fij,fkj->fki", r, p - p[:, :1])


def _best_frames(var: np.ndarray, seen: np.ndarray, frames: np.ndarray, fraction: float):
    """The `fraction` of `frames` with the lowest mean variance over the given LEDs."""
    v = np.where(seen, var, np.nan)
    with np.errstate(all="ignore"):
        score = np.nanmean(v, axis=1)
    score = np.where(np.isfinite(score), score, np.inf)
    k = max(3, int(np.ceil(fraction * frames.size)))
    order = np.argsort(score, kind="stable")[:k]
    return frames[np.sort(order)]


def register_leds(
    positions: np.ndarray,
    variance: np.ndarray,
    segments: list[tuple[int, int]],
    led_ids: np.ndarray,
    reference_leds: np.ndarray,
    nominal: np.ndarray | None = None,
    *,
    fraction: float = 0.5,
    passes: int = 2,
) -> Registration:
    """Register every LED's tool-frame position from static segments.

    positions `(N, M, 3)` [m] camera frame, NaN unseen; variance `(N, M)` [m²] (the
    paper's LED variance); segments: static frame ranges; nominal `(M, 3)` optional.
    """
    led_ids = np.asarray(led_ids)
    m = led_ids.size
    if not segments:
        raise UserError("no static segment found: LED registration needs the tool at rest")
    idx = {int(i): k for k, i in enumerate(led_ids)}
    missing = [int(r) for r in reference_leds if int(r) not in idx]
    if missing:
        raise UserError(f"reference LEDs {missing} are not in the recording's LED ids")
    ref = np.array([idx[int(r)] for r in reference_leds])
    seen = np.all(np.isfinite(positions), axis=-1)
    var = np.where(np.isfinite(variance), variance, np.inf)

    # 1. reference LEDs from the static frames where all three are seen
    ref_frames = np.concatenate([np.arange(a, b)[seen[a:b][:, ref].all(1)] for a, b in segments])
    if ref_frames.size < 3:
        raise UserError(
            "the three reference LEDs "
            f"{[int(r) for r in reference_leds]} are never seen together while the tool is at rest"
        )
    best = _best_frames(var[ref_frames][:, ref], seen[ref_frames][:, ref], ref_frames, fraction)
    # their shape (inter-LED distances) from frame-wise triangles in their own frame
    tri = _frames_from_three(positions[best][:, ref])
    tri_mean = tri.mean(0)
    if nominal is not None:
        # as one frame of all M LEDs (the others weight 0): the segments' kernel
        model = np.zeros((m, 3))
        model[ref] = tri_mean
        weights = np.zeros((1, m))
        weights[0, ref] = 1.0
        fit = _fit(model, np.asarray(nominal, np.float64)[None], weights)
        r = _quat_matrix(fit["quaternion_wxyz"])[0]
        ref_pos = tri_mean @ r.T + fit["position"][0]
        gauge = "reference LEDs fitted to the nominal constellation (nominal TCP)"
    else:
        ref_pos = tri_mean
        gauge = "reference-LED frame (origin LED 1st, x toward 2nd, z normal to their plane)"

    pos = np.full((m, 3), np.nan)
    unc = np.full(m, np.nan)
    count = np.zeros(m, np.int64)
    pos[ref] = ref_pos
    unc[ref] = tri.std(0, ddof=1).mean(0).mean() / np.sqrt(len(best)) if len(best) > 1 else np.nan
    count[ref] = len(best)
    known = np.zeros(m, bool)
    known[ref] = True
    frozen = known.copy()  # the reference LEDs define the gauge and are not re-estimated

    for p in range(passes):
        grew = True
        current = pos.copy()
        usable = known.copy()
        new_pos = np.where(frozen[:, None], pos, np.nan)
        new_unc = np.where(frozen, unc, np.nan)
        new_cnt = np.where(frozen, count, 0)
        while grew:
            grew = False
            sums = np.zeros((m, 3))
            sq = np.zeros((m, 3))
            cnt = np.zeros(m)
            for a, b in segments:
                fr = np.arange(a, b)
                use = seen[a:b] & usable[None]
                ok = use.sum(1) >= 3
                if not ok.any():
                    continue
                fr = _best_frames(var[fr[ok]], use[ok], fr[ok], fraction)
                w = np.where(seen[fr] & usable[None], 1.0 / np.maximum(var[fr], 1e-18), 0.0)
                w = np.where(
                    np.isfinite(w) & (w > 0), w, np.where(seen[fr] & usable[None], 1.0, 0.0)
                )
                fit = _fit(np.nan_to_num(current), positions[fr], w)
                valid = fit["valid"]
                if not valid.any():
                    continue
                rmat = _quat_matrix(fit["quaternion_wxyz"][valid])
                t = fit["position"][valid]
                y = positions[fr][valid]  # (F, M, 3)
                local = np.einsum("fji,fmj->fmi", rmat, y - t[:, None, :])
                target = ~frozen if p > 0 else ~usable
                s = seen[fr][valid] & target[None]
                sums += np.where(s[..., None], local, 0.0).sum(0)
                sq += np.where(s[..., None], local**2, 0.0).sum(0)
                cnt += s.sum(0)
            fresh = (cnt >= 3) & (np.isnan(new_pos[:, 0]))
            if fresh.any():
                mean = sums[fresh] / cnt[fresh, None]
                var_k = np.maximum(sq[fresh] / cnt[fresh, None] - mean**2, 0.0)
                new_pos[fresh] = mean
                new_unc[fresh] = np.sqrt(var_k.mean(1) / np.maximum(cnt[fresh] - 1, 1))
                new_cnt[fresh] = cnt[fresh]
                if p == 0:
                    current[fresh] = mean
                    usable |= fresh
                    grew = True
        pos, unc, count = new_pos, new_unc, new_cnt
        known = np.isfinite(pos[:, 0])

    reasons = {}
    for k in np.flatnonzero(~known):
        if not seen[:, k].any():
            reasons[int(led_ids[k])] = "never seen"
        elif not any(seen[a:b, k].any() for a, b in segments):
            reasons[int(led_ids[k])] = "never seen while the tool was at rest"
        else:
            reasons[int(led_ids[k])] = (
                "never seen at rest together with at least three referenced LEDs"
            )
    return Registration(led_ids, pos, unc, count.astype(np.int64), reasons, gauge)


def _fit(model: np.ndarray, measured: np.ndarray, weights: np.ndarray) -> dict[str, np.ndarray]:
    """`weighted_procrustes` as numpy arrays, over blocks of `_BLOCK` frames padded in
    numpy (weight 0): one compiled kernel for any number of frames."""
    n = measured.shape[0]
    parts = []
    for a in range(0, n, _BLOCK):
        k = min(_BLOCK, n - a)
        y = np.zeros((_BLOCK, *measured.shape[1:]))
        w = np.zeros((_BLOCK, weights.shape[1]))
        y[:k], w[:k] = measured[a : a + k], weights[a : a + k]
        fit = weighted_procrustes(jnp.asarray(model), jnp.asarray(y), jnp.asarray(w))
        parts.append(
            {f: np.asarray(getattr(fit, f))[:k] for f in ("quaternion_wxyz", "position", "valid")}
        )
    return {f: np.concatenate([p[f] for p in parts]) for f in parts[0]}


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices `(F, 3, 3)` of unit quaternions `(F, 4)` (w, x, y, z), numpy."""
    rows = rotation_rows(*np.moveaxis(np.asarray(q, np.float64), -1, 0))
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)
