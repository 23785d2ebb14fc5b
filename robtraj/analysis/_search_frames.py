"""The frames a discrepancy search runs on: a long recording's evenly spaced subset.

The search's arrays are per observation (residuals of every fit, weights, emission
angles, the localisation's variables: about 3.4 kB a frame with 18 LEDs), so a search
over an hour at 1 kHz would need ~12 GB. A longer recording than `SEARCH_FRAMES` is
therefore searched on every k-th frame (evenly spaced, so drifts and every part of the
program are covered), and the named model is fitted again on all frames, out of core
(`refit_on_all_frames`). The price is sensitivity: the floor of the gap falls as
N^(-1/4), so the subset of 10⁵ frames names effects down to ~8 µm RMS where an hour's
3.6·10⁶ frames would reach ~3 µm.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..recording import Recording

#: the most frames a discrepancy search holds
SEARCH_FRAMES = 100_000
#: frames read at a time when taking the subset
_READ = 1 << 16


def search_step(n_frames: int, max_frames: int | None = None) -> int:
    """Every how many frames the search takes one of a recording of `n_frames` (at most
    `max_frames`, default `SEARCH_FRAMES`)."""
    return max(1, -(-n_frames // (max_frames or SEARCH_FRAMES)))


def search_recording(rec: Recording, max_frames: int | None = None) -> tuple[Recording, int]:
    """`(recording, k)` in memory: every k-th frame of `rec` (k = ⌈N / max_frames⌉, default
    `SEARCH_FRAMES`; all of them when N ≤ `max_frames`), the LED positions and status read a block at a time
    from `rec` (which may be opened lazily): time, frame index, positions, status,
    temperature and the program's per-frame segment are subsampled; the robot log, tool
    and program targets kept whole; truth and extra datasets left out."""
    n = rec.n_frames
    k = search_step(n, max_frames)
    take = np.arange(0, n, k)
    block = k * -(-_READ // k)  # a multiple of k: each block's rows 0, k, 2k, … are taken

    def strided(x):
        if x is None:
            return None
        return np.concatenate([np.asarray(x[a : a + block])[::k] for a in range(0, n, block)])

    program = rec.program
    if program is not None and program.segment is not None:
        program = dataclasses.replace(program, segment=np.asarray(program.segment)[take])
    sub = rec.replace(
        time=np.asarray(rec.time)[take],
        frame_index=np.asarray(rec.frame_index)[take],
        positions=strided(rec.positions),
        status=strided(rec.status),
        temperature=None if rec.temperature is None else np.asarray(rec.temperature)[take],
        program=program,
        truth=None,
        extras={},
        extra_attrs={},
    )
    return sub, k


def refit_on_all_frames(rec: Recording, calibration, progress=None):
    """The model of `calibration` (a discrepancy search's final fit, on a subset of
    `rec`'s frames) fitted on every frame of `rec` from it, as `robtraj calibrate`
    fits (out of core, the recording's own noise model, robust σ)."""
    from ..estimate.calibration import fit

    return fit(
        rec,
        estimate=tuple(calibration.estimated),
        init=calibration,
        progress=progress,
        per_observation=False,
    )
