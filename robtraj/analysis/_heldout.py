"""The held-out check of the discrepancy search: the gap of a model on the time blocks it
was not fitted to."""

from __future__ import annotations

import numpy as np

from ..recording import Recording
from ._residual_stats import aligned

#: contiguous time blocks of the held-out check; odd and even blocks are the two folds
HELDOUT_BLOCKS = 8


class HeldOut:
    """Two-fold cross-validation over contiguous time blocks (odd against even): the
    gap of a model on the blocks it was not fitted to [m], over the LEDs that the
    blocks it was fitted to see (an LED seen only in the held-out blocks has no
    position the fit could determine)."""

    def __init__(self, rec: Recording, weights: np.ndarray, var: np.ndarray):
        from ..estimate.calibration import fit, predict_residuals

        self._fit, self._predict = fit, predict_residuals
        n = rec.n_frames
        #: `(N,)` the time block (0 … `HELDOUT_BLOCKS` − 1) of each frame; its parity is the fold
        self.block = np.arange(n) * HELDOUT_BLOCKS // n
        self.fold = self.block % 2
        self.rec, self.weights, self.var3 = rec, weights, 3.0 * var

    def gap(self, estimate: tuple[str, ...], init, space: tuple[str, ...] = ()) -> float:
        r2, v3 = [], []
        for f in (0, 1):
            train = np.where((self.fold != f)[:, None], self.weights, 0.0)
            res = self._fit(
                self.rec,
                estimate=estimate,
                weights=train,
                init=init,
                space=space,
                robust_sigma=False,
            )
            d = self._predict(self.rec, res, space)[self.fold == f]
            v = aligned(self.rec, res, self.var3)[self.fold == f]
            trained = np.any(aligned(self.rec, res, train) > 0, axis=0)
            use = np.isfinite(d[..., 0]) & np.isfinite(v) & trained[None, :]
            r2.append(np.sum(d[use] ** 2, -1))
            v3.append(v[use])
        r2, v3 = np.concatenate(r2), np.concatenate(v3)
        return float(np.sqrt(max(0.0, np.mean(r2) - np.mean(v3))))
