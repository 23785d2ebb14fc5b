"""The residuals of a bundle fit at its estimate (`Residuals`), summarised as the result
reports them: RMS per frame and per LED, and what makes a frame stand out; in one pass
over the frames, block by block (the `(frames, leds, 3)` residuals themselves only when
asked for)."""

from __future__ import annotations

import dataclasses

import numpy as np

from ._calib_problem import over_residuals
from ._calib_setup import Setup
from ._calib_solves import Solved
from ._exact_median import ExactMedian

#: the emission angle below which this fraction of the observations were seen
SEEN_FRACTION = 0.99


@dataclasses.dataclass(frozen=True)
class Residuals:
    """Measured − predicted at the estimate, over the observations of non-zero weight:
    `residuals` `(recording frames, leds, 3)` [m] (NaN elsewhere; None unless asked
    for), their mean squared norm [m²], their RMS [m] per recording frame and per LED
    id, and per recording frame the mean square per axis of the residuals normalised by
    the noise model (`frame_noise_square`: over the variance factor, a frame's outlier
    statistic); NaN for frames without observations. `seen_angle` [rad]: the emission
    angle below which 99 % of the observations were seen (π without LED normals).
    `weights` `(frames, leds)` [1/m²]: the last solve's, where `residuals` are asked
    for; their log sum ``Σ log w`` and count over the observations of non-zero weight
    (`log_weight_sum`, `n_used`), the noise weights' mean there (`mean_weight`), the
    sum of each frame's weights (`frame_weight` `(frames,)`) and the median of the
    non-zero weights (`median_weight`, with the cluster-robust covariance only)."""

    residuals: np.ndarray | None
    mean_square: float
    rms_per_frame: np.ndarray
    rms_per_led: dict[int, float]
    frame_noise_square: np.ndarray
    seen_angle: float
    weights: np.ndarray | None = None
    log_weight_sum: float = 0.0
    n_used: int = 0
    mean_weight: float = float("nan")
    frame_weight: np.ndarray | None = None
    median_weight: float = float("nan")


def residuals_at(st: Setup, solved: Solved, full: bool | None = None) -> Residuals:
    """The residuals of `solved`'s estimate (weights of the noise model: the blocks'
    own, before a robust loss's factor); `full`: keep the `(frames, leds, 3)` residuals
    and the weights (default: `st.per_observation`)."""
    data = st.data
    full = st.per_observation if full is None else full
    n_rec, m = data.n_recording_frames, data.n_leds
    out = np.full((n_rec, m, 3), np.nan) if full else None
    weights = np.zeros((data.n_frames, m)) if full else None
    per_frame = np.full(n_rec, np.nan)
    noise_square = np.full(n_rec, np.nan)
    sums = {"sq": 0.0, "n": 0, "logw": 0.0, "w": 0.0}
    led_sq, led_n = np.zeros(m), np.zeros(m, np.int64)
    frame_weight = np.zeros(data.n_frames)
    median = ExactMedian()
    top = Quantile(int(np.sum(st.used)), SEEN_FRACTION) if data.has_normals else None

    def visit(block, d, theta):
        a, b = block.a, block.b
        used, w = block.noise > 0, block.weights
        sq = np.einsum("fli,fli->fl", d, d)  # no (frames, leds, 3) temporary
        if top is not None:
            top.add(theta[used])
        cnt = used.sum(1)
        sq_used = sq * used
        with np.errstate(invalid="ignore", divide="ignore"):
            per_frame[data.frame[a:b]] = np.where(cnt > 0, np.sqrt(sq_used.sum(1) / cnt), np.nan)
            u2 = np.sum(block.noise * sq_used, 1) / np.maximum(3 * cnt, 1)
        noise_square[data.frame[a:b]] = np.where(cnt > 0, u2, np.nan)
        led_sq[:] += sq_used.sum(0)
        led_n[:] += used.sum(0)
        sums["sq"] += float(sq[used].sum())
        sums["n"] += int(used.sum())
        sums["logw"] += float(np.sum(np.log(w[used])))
        sums["w"] += float(np.sum(block.noise[used]))
        frame_weight[a:b] = w.sum(1)
        median.count(w[w > 0])
        if full:
            rows = data.frame[a:b]
            out[rows] = np.where(used[..., None], d, np.nan)
            weights[a:b] = w

    over_residuals(solved.bundle, st.q, visit)
    if st.clustered:  # the median's second pass: the weights alone
        solved.bundle.chunks.blocks(
            lambda _block: None, lambda block, _: median.keep(block.weights[block.weights > 0])
        )
    with np.errstate(invalid="ignore", divide="ignore"):
        per_led = np.sqrt(led_sq / led_n)
    n = max(sums["n"], 1)
    return Residuals(
        residuals=out,
        mean_square=sums["sq"] / n,
        rms_per_frame=per_frame,
        rms_per_led={int(i): float(v) for i, v in zip(data.led_ids, per_led) if np.isfinite(v)},
        frame_noise_square=noise_square,
        seen_angle=top.value() if top is not None else np.pi,
        weights=weights,
        log_weight_sum=sums["logw"],
        n_used=sums["n"],
        mean_weight=sums["w"] / n,
        frame_weight=frame_weight,
        median_weight=median.value() if st.clustered else float("nan"),
    )


class Quantile:
    """The `q`-quantile of `n` values that arrive block by block (``np.quantile``'s
    linear interpolation, exactly): only the values that can hold its ranks are kept."""

    def __init__(self, n: int, q: float) -> None:
        self.n, self.q = n, q
        # numpy's virtual index of the linear method, computed as numpy computes it
        self.h = n * q + (1 + q * (1 - 1 - 1)) - 1
        self.lo = int(np.floor(self.h))
        self.keep = max(n - self.lo, 1)
        self.kept = np.zeros(0)

    def add(self, values: np.ndarray) -> None:
        v = np.concatenate([self.kept, np.ravel(values)])
        if v.size > self.keep:
            v = np.partition(v, v.size - self.keep)[v.size - self.keep :]
        self.kept = v

    def value(self) -> float:
        if self.n == 0 or self.kept.size == 0:
            return float("nan")
        v = np.sort(self.kept)
        first = self.n - v.size  # rank of v[0]
        i = min(max(self.lo - first, 0), v.size - 1)
        a, b = v[i], v[min(i + 1, v.size - 1)]
        t = self.h - self.lo
        diff = b - a
        return float(b - diff * (1 - t) if t >= 0.5 else a + diff * t)
