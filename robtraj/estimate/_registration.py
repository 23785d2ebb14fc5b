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
from collections.abc import Callable, Iterator

import jax.numpy as jnp
import numpy as np

from .._errors import UserError
from ..jax_ops import rotation_rows, weighted_procrustes
from ..recording import FrameArray, finite_points

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


@dataclasses.dataclass(frozen=True)
class Piece:
    """Consecutive static frames ``start .. start + F - 1`` of segment number `segment`:
    their `positions` `(F, M, 3)` [m] (NaN unseen) and paper LED `variance` `(F, M)` [m²]."""

    segment: int
    start: int
    positions: np.ndarray
    variance: np.ndarray


#: a new iterator over the static frames as `Piece`s, segment by segment in the order of
#: the segments, each segment's frames in order
Pieces = Callable[[], Iterator[Piece]]
_PIECE = 8192  # frames per piece of `array_pieces`


def array_pieces(
    positions: FrameArray, variance: np.ndarray, segments: list[tuple[int, int]]
) -> Pieces:
    """The static frames of in-memory `positions` `(N, M, 3)` and `variance` `(N, M)`."""

    def pieces() -> Iterator[Piece]:
        for j, (a, b) in enumerate(segments):
            for s in range(a, b, _PIECE):
                e = min(b, s + _PIECE)
                yield Piece(j, s, np.asarray(positions[s:e], np.float64), np.asarray(variance[s:e]))

    return pieces


def register_leds(
    positions: FrameArray,
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
    ever_seen = np.zeros(positions.shape[1], bool)
    for a in range(0, positions.shape[0], _PIECE):
        ever_seen |= finite_points(np.asarray(positions[a : a + _PIECE])).any(0)
    return register_pieces(
        array_pieces(positions, variance, segments),
        segments,
        led_ids,
        reference_leds,
        nominal,
        ever_seen,
        fraction=fraction,
        passes=passes,
    )


class _Static:
    """Passes over the static frames: per static frame (segments concatenated in order)
    only counts, scores and selections stay in memory."""

    def __init__(
        self, pieces: Pieces, segments: list[tuple[int, int]], m: int, say: Callable
    ) -> None:
        self._pieces, self._say, self._passes = pieces, say, 0
        self.segments = segments
        lengths = np.array([b - a for a, b in segments], np.int64)
        self.offset = np.concatenate([[0], np.cumsum(lengths)])
        self.m = m
        self.at_rest = np.zeros(m, bool)  # LEDs seen in a static frame (first pass)
        self._cache: tuple[bytes, np.ndarray, np.ndarray] | None = None

    @property
    def size(self) -> int:
        return int(self.offset[-1])

    def pieces(self) -> Iterator[Piece]:
        self._passes += 1
        self._say(f"pass {self._passes} over the {self.size:,} frames at rest")
        return self._pieces()

    def rows(self, p: Piece) -> slice:
        """The static-frame indices of piece `p`."""
        first = int(self.offset[p.segment]) + p.start - self.segments[p.segment][0]
        return slice(first, first + p.positions.shape[0])

    def segment_rows(self, j: int) -> np.ndarray:
        return np.arange(self.offset[j], self.offset[j + 1])

    def scores(self, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per static frame: the number of `usable` LEDs seen and their mean variance
        (inf where not finite; only where at least three are seen)."""
        key = usable.tobytes()
        if self._cache is None or self._cache[0] != key:
            self._cache = (key, *self._scores(usable, None)[:2])
        return self._cache[1], self._cache[2]

    def reference_scores(self, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per static frame: whether all `ref` LEDs are seen, and their mean variance
        there (inf elsewhere). Also caches `scores` of the reference LEDs."""
        usable = np.isin(np.arange(self.m), ref)
        count, score, ref_all, ref_score = self._scores(usable, ref)
        self._cache = (usable.tobytes(), count, score)
        return ref_all, ref_score

    def _scores(self, usable: np.ndarray, ref: np.ndarray | None):
        count = np.zeros(self.size, np.int64)
        score = np.full(self.size, np.inf)
        ref_all = np.zeros(self.size, bool)
        ref_score = np.full(self.size, np.inf)
        for p in self.pieces():
            seen = finite_points(p.positions)
            self.at_rest |= seen.any(0)
            var = np.where(np.isfinite(p.variance), p.variance, np.inf)
            use = seen & usable[None]
            n_use = use.sum(1)
            rows = self.rows(p)
            count[rows] = n_use
            score[rows] = _mean_score(var, use, n_use >= 3)
            if ref is not None:
                all_seen = seen[:, ref].all(1)
                ref_all[rows] = all_seen
                ref_score[rows] = _mean_score(var[:, ref], seen[:, ref], all_seen)
        return count, score, ref_all, ref_score

    def visit(self, selected: np.ndarray) -> Iterator[tuple[Piece, np.ndarray]]:
        """The pieces holding `selected` static frames, with their selected rows."""
        for p in self.pieces():
            sel = selected[self.rows(p)]
            if sel.any():
                yield p, sel


def _mean_score(var: np.ndarray, use: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Mean of `var` over the `use` LEDs of each frame (inf where not finite) in `rows`
    (inf elsewhere): the frame's quality for `_best`."""
    out = np.full(var.shape[0], np.inf)
    if rows.any():
        with np.errstate(all="ignore"):
            score = np.nanmean(np.where(use[rows], var[rows], np.nan), axis=1)
        out[rows] = np.where(np.isfinite(score), score, np.inf)
    return out


def _best(score: np.ndarray, candidates: np.ndarray, fraction: float) -> np.ndarray:
    """The `fraction` of the `candidates` (static-frame indices, in order) with the lowest
    score (at least three), in order."""
    k = max(3, int(np.ceil(fraction * candidates.size)))
    order = np.argsort(score[candidates], kind="stable")[:k]
    return candidates[np.sort(order)]


def register_pieces(
    pieces: Pieces,
    segments: list[tuple[int, int]],
    led_ids: np.ndarray,
    reference_leds: np.ndarray,
    nominal: np.ndarray | None,
    ever_seen: np.ndarray,
    *,
    fraction: float = 0.5,
    passes: int = 2,
    say: Callable[[str], None] = lambda message: None,
) -> Registration:
    """`register_leds` from the static frames as `pieces` (see `Pieces`; every round of
    the algorithm passes over them once or twice) and `ever_seen` `(M,)`: which LEDs the
    recording sees at all. `say` hears of each pass."""
    led_ids = np.asarray(led_ids)
    m = led_ids.size
    if not segments:
        raise UserError("no static segment found: LED registration needs the tool at rest")
    idx = {int(i): k for k, i in enumerate(led_ids)}
    missing = [int(r) for r in reference_leds if int(r) not in idx]
    if missing:
        raise UserError(f"reference LEDs {missing} are not in the recording's LED ids")
    ref = np.array([idx[int(r)] for r in reference_leds])
    static = _Static(pieces, segments, m, say)

    # 1. reference LEDs from the static frames where all three are seen
    known = np.zeros(m, bool)
    known[ref] = True
    ref_all, ref_score = static.reference_scores(ref)
    ref_frames = np.flatnonzero(ref_all)
    if ref_frames.size < 3:
        raise UserError(
            "the three reference LEDs "
            f"{[int(r) for r in reference_leds]} are never seen together while the tool is at rest"
        )
    best = np.zeros(static.size, bool)
    best[_best(ref_score, ref_frames, fraction)] = True
    # their shape (inter-LED distances) from frame-wise triangles in their own frame
    n_best, tri_mean, tri_m2 = 0, np.zeros((3, 3)), np.zeros((3, 3))
    for p, sel in static.visit(best):
        tri = _frames_from_three(p.positions[sel][:, ref])
        n_best, tri_mean, tri_m2 = _merge_moments(n_best, tri_mean, tri_m2, tri)
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
    if n_best > 1:
        unc[ref] = np.sqrt(tri_m2 / (n_best - 1)).mean(0).mean() / np.sqrt(n_best)
    count[ref] = n_best
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
            target = ~frozen if p > 0 else ~usable
            sums, sq, cnt = _local_sums(static, usable, current, target, fraction)
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
        if not ever_seen[k]:
            reasons[int(led_ids[k])] = "never seen"
        elif not static.at_rest[k]:
            reasons[int(led_ids[k])] = "never seen while the tool was at rest"
        else:
            reasons[int(led_ids[k])] = (
                "never seen at rest together with at least three referenced LEDs"
            )
    return Registration(led_ids, pos, unc, count.astype(np.int64), reasons, gauge)


def _merge_moments(n: int, mean: np.ndarray, m2: np.ndarray, x: np.ndarray):
    """Count, mean and sum of squared deviations over axis 0 of the samples so far
    (`n`, `mean`, `m2`) and those of `x` (Chan et al.'s pairwise update)."""
    k = x.shape[0]
    if k == 0:
        return n, mean, m2
    mean_x = x.mean(0)
    m2_x = ((x - mean_x) ** 2).sum(0)
    total = n + k
    delta = mean_x - mean
    return total, mean + delta * (k / total), m2 + m2_x + delta**2 * (n * k / total)


def _local_sums(static: _Static, usable, current, target, fraction):
    """One round of registration: in each segment, the best frames where three usable
    LEDs are seen are fitted (poses of `current`), and every `target` LED seen there is
    expressed in the tool frame: per-LED sums, sums of squares and counts."""
    m = static.m
    sums = np.zeros((m, 3))
    sq = np.zeros((m, 3))
    cnt = np.zeros(m)
    n_use, score = static.scores(usable)
    selected = np.zeros(static.size, bool)
    for j in range(len(static.segments)):
        rows = static.segment_rows(j)
        ok = rows[n_use[rows] >= 3]
        if ok.size:
            selected[_best(score, ok, fraction)] = True
    model = np.nan_to_num(current)
    for p, sel in static.visit(selected):
        y_all = p.positions[sel]
        seen = finite_points(y_all)
        var = np.where(np.isfinite(p.variance[sel]), p.variance[sel], np.inf)
        w = np.where(seen & usable[None], 1.0 / np.maximum(var, 1e-18), 0.0)
        w = np.where(np.isfinite(w) & (w > 0), w, np.where(seen & usable[None], 1.0, 0.0))
        fit = _fit(model, y_all, w)
        valid = fit["valid"]
        if not valid.any():
            continue
        rmat = _quat_matrix(fit["quaternion_wxyz"][valid])
        t = fit["position"][valid]
        y = y_all[valid]  # (F, M, 3)
        local = np.einsum("fji,fmj->fmi", rmat, y - t[:, None, :])
        s = seen[valid] & target[None]
        sums += np.where(s[..., None], local, 0.0).sum(0)
        sq += np.where(s[..., None], local**2, 0.0).sum(0)
        cnt += s.sum(0)
    return sums, sq, cnt


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
