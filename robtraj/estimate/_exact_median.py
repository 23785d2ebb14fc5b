"""The exact median of values that arrive chunk by chunk, in two passes and small memory.

Pass 1 (`count`) histograms the values on their float64 bit patterns (an order-preserving
key, so each bin is a contiguous range of values); pass 2 (`keep`) keeps only the values
in the bins that hold the middle rank(s), a small fraction; `value` sorts those. The
result is the median of all values exactly, as ``np.median`` (mean of the two middle
values for an even count) and ``jnp.nanmedian`` give it.
"""

from __future__ import annotations

import numpy as np

_SHIFT = 44  # bins: the sign, the exponent and 8 mantissa bits (1/256 of an octave)


def _keys(values: np.ndarray) -> np.ndarray:
    """Order-preserving uint64 keys of finite float64 `values`."""
    bits = np.ascontiguousarray(values, np.float64).view(np.uint64)
    negative = (bits >> np.uint64(63)).astype(bool)
    return np.where(negative, ~bits, bits | np.uint64(1 << 63))


class ExactMedian:
    """Median of all finite values passed to `count` (pass 1), the same values passed
    again to `keep` (pass 2), in any chunking; NaN when there are none."""

    def __init__(self) -> None:
        self._counts = np.zeros(1 << (64 - _SHIFT), np.int64)
        self._bins: np.ndarray | None = None
        self._ranks: tuple[int, int] | None = None
        self._kept: list[np.ndarray] = []

    def count(self, values: np.ndarray) -> None:
        v = np.ravel(values)
        v = v[np.isfinite(v)]
        self._counts += np.bincount(
            (_keys(v) >> np.uint64(_SHIFT)).astype(np.int64), minlength=self._counts.size
        )

    @property
    def n(self) -> int:
        return int(self._counts.sum())

    def _select(self) -> None:
        n = self.n
        lo, hi = (n - 1) // 2, n // 2  # the middle rank(s), 0-based
        cum = np.cumsum(self._counts)
        b_lo, b_hi = np.searchsorted(cum, [lo + 1, hi + 1])
        self._bins = np.array(sorted({int(b_lo), int(b_hi)}), np.uint64)
        below = int(cum[b_lo - 1]) if b_lo > 0 else 0
        self._ranks = (lo - below, hi - below)

    def needed(self) -> bool:
        """Whether pass 2 is needed (False when there are no values)."""
        return self.n > 0

    def keep(self, values: np.ndarray) -> None:
        if self._bins is None:
            self._select()
        v = np.ravel(values)
        v = v[np.isfinite(v)]
        self._kept.append(v[np.isin(_keys(v) >> np.uint64(_SHIFT), self._bins)])

    def value(self) -> float:
        if self.n == 0:
            return float("nan")
        if self._bins is None:
            self._select()
        kept = np.sort(np.concatenate(self._kept)) if self._kept else np.zeros(0)
        lo, hi = self._ranks
        if kept.size <= hi:
            raise RuntimeError("ExactMedian: pass 2 did not see the values of pass 1")
        return float((kept[lo] + kept[hi]) * 0.5)
