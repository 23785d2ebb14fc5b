"""The residuals of a bundle fit at its estimate (`Residuals`), summarised as the result
reports them: RMS per frame and per LED, and what makes a frame stand out."""

from __future__ import annotations

import dataclasses

import numpy as np

from ._calib_problem import at_estimate
from ._calib_setup import Setup
from ._calib_solves import Solved


@dataclasses.dataclass(frozen=True)
class Residuals:
    """Measured − predicted at the estimate, over the observations of non-zero weight:
    `residuals` `(recording frames, leds, 3)` [m] (NaN elsewhere), their mean squared
    norm [m²], their RMS [m] per recording frame and per LED id, and per recording
    frame the mean square per axis of the residuals normalised by the noise model
    (`frame_noise_square`: over the variance factor, a frame's outlier statistic); NaN
    for frames without observations. `seen_angle` [rad]: the emission angle below which
    99 % of the observations were seen (π without LED normals)."""

    residuals: np.ndarray
    mean_square: float
    rms_per_frame: np.ndarray
    rms_per_led: dict[int, float]
    frame_noise_square: np.ndarray
    seen_angle: float


def residuals_at(st: Setup, solved: Solved) -> Residuals:
    """The residuals of `solved`'s estimate (weights of the noise model: `solved`'s)."""
    data, used = st.data, st.used
    d, theta, sq = at_estimate(solved.bundle, st.q, data.n_frames)
    seen_angle = float(np.quantile(theta[used], 0.99)) if data.has_normals else np.pi
    del theta
    full = np.full((data.n_recording_frames, data.n_leds, 3), np.nan)
    full[data.frame] = d
    del d
    unused_frame, unused_led = np.nonzero(~used)
    full[data.frame[unused_frame], unused_led] = np.nan
    per_frame = np.full(data.n_recording_frames, np.nan)
    noise_square = np.full(data.n_recording_frames, np.nan)
    cnt = used.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_frame[data.frame] = np.where(cnt > 0, np.sqrt(np.sum(sq * used, 1) / cnt), np.nan)
        per_led = np.sqrt(np.sum(sq * used, 0) / used.sum(0))
        u2 = np.sum(solved.noise_weights * sq * used, 1) / np.maximum(3 * cnt, 1)
    noise_square[data.frame] = np.where(cnt > 0, u2, np.nan)
    return Residuals(
        residuals=full,
        mean_square=float(np.mean(sq[used])),
        rms_per_frame=per_frame,
        rms_per_led={int(i): float(v) for i, v in zip(data.led_ids, per_led) if np.isfinite(v)},
        frame_noise_square=noise_square,
        seen_angle=seen_angle,
    )
