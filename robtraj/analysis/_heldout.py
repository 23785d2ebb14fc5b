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
        """The held-out gap [m] of the model estimating `estimate`; `init` is its fit to
        the whole recording (`CalibrationResult`), from which each fold's fit is one
        Gauss–Newton step; `space` that fit's space."""
        r2, v3 = [], []
        for f, res, d in self._folds(estimate, init, space):
            v = aligned(self.rec, res, self.var3)[self.fold == f]
            use = np.isfinite(d[..., 0]) & np.isfinite(v)
            r2.append(np.sum(d[use] ** 2, -1))
            v3.append(v[use])
        r2, v3 = np.concatenate(r2), np.concatenate(v3)
        return float(np.sqrt(max(0.0, np.mean(r2) - np.mean(v3))))

    def chi2(self, estimate: tuple[str, ...], init, space: tuple[str, ...] = ()) -> np.ndarray:
        """`(N, M)` each observation's weighted squared held-out residual (the recording's
        LED columns; NaN where the gap leaves it out)."""
        out = np.full(self.weights.shape, np.nan)
        col = {int(i): k for k, i in enumerate(np.asarray(self.rec.led_ids))}
        for f, res, d in self._folds(estimate, init, space):
            w = aligned(self.rec, res, self.weights)[self.fold == f]
            cols = [col[int(i)] for i in res.led_ids]
            rows = np.flatnonzero(self.fold == f)
            out[np.ix_(rows, cols)] = np.where(np.isfinite(d[..., 0]), np.sum(d**2, -1) * w, np.nan)
        return out

    def _folds(self, estimate, init, space):
        """Per fold: the fit to the other fold and its residuals `(n_f, M, 3)` [m] on this
        one, NaN for LEDs the training fold did not see. The fit is one Gauss–Newton
        step from `init`, the fit to both folds: half the observations move the
        optimum by about its σ, over which the problem is linear to far below the
        noise (one pass instead of one per solver step)."""
        for f in (0, 1):
            train = np.where((self.fold != f)[:, None], self.weights, 0.0)
            res = self._fit(
                self.rec,
                estimate=estimate,
                weights=train,
                init=init,
                space=space,
                robust_sigma=False,
                one_step=True,
            )
            d = self._predict(self.rec, res, space)[self.fold == f]
            trained = np.any(aligned(self.rec, res, train) > 0, axis=0)
            yield f, res, np.where(trained[None, :, None], d, np.nan)


def vuong(chi2_a: np.ndarray, chi2_b: np.ndarray) -> tuple[float, float]:
    """Vuong's test of two non-nested models on the same held-out observations
    (`HeldOut.chi2` of each, `(N, M)`): per frame the log-likelihood ratio
    ``δ = ½ Σ_LEDs (χ²_b − χ²_a)`` over the observations both have; returns
    ``z = Σδ / (√F · sd(δ))`` over the F frames (positive: `b` fits worse; normal under
    equally good models) and ``2 Σδ``, the held-out χ² by which `b` is worse."""
    both = np.isfinite(chi2_a) & np.isfinite(chi2_b)
    per_frame = 0.5 * np.sum(np.where(both, chi2_b - chi2_a, 0.0), axis=1)[both.any(axis=1)]
    total = float(per_frame.sum())
    sd = float(per_frame.std(ddof=1)) if per_frame.size > 1 else 0.0
    z = total / (np.sqrt(per_frame.size) * sd) if sd > 0 else 0.0
    return z, 2.0 * total
