"""95 % confidence intervals of ISO 9283 characteristics from their cycles.

Where the sampling distribution is known for normally scattered cycles the interval is
exact: Student's t for a mean (AP components, AD, AV, mean stabilisation time, …) and
the χ² interval for a 3·S term (RD, RV, RP per orientation component). Every other
characteristic (lengths of means, l̄ + 3·S_l, maxima over planes, differences between
groups of cycles) gets a bias-corrected and accelerated (BCa) bootstrap over cycles,
stratified where cycles fall into groups (approach directions, early/late cycles): the
plain percentile bootstrap under-covers with few cycles, BCa corrects its first-order
bias and skew (Efron 1987). Statistics are vectorised over leading batch axes so a
whole bootstrap is one array expression.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy import special, stats

LEVEL = 0.95
N_BOOT = 2000

Interval = tuple[float, float]
NAN_INTERVAL: Interval = (float("nan"), float("nan"))


def t_interval(x: np.ndarray) -> tuple[Any, Any]:
    """Student-t interval of the mean of `x` over axis 0 (cycles); NaN with < 2 cycles."""
    x = np.asarray(x, np.float64)
    n = x.shape[0]
    if n < 2:
        nan = np.full(x.shape[1:], np.nan)
        return nan, nan
    half = stats.t.ppf(0.5 + LEVEL / 2, n - 1) * np.std(x, axis=0, ddof=1) / np.sqrt(n)
    m = x.mean(axis=0)
    return m - half, m + half


def three_s_interval(x: np.ndarray) -> tuple[Any, Any]:
    """χ² interval of 3·σ from the sample standard deviation of `x` over axis 0."""
    x = np.asarray(x, np.float64)
    n = x.shape[0]
    if n < 2:
        nan = np.full(x.shape[1:], np.nan)
        return nan, nan
    s3 = 3.0 * np.std(x, axis=0, ddof=1)
    lo = s3 * np.sqrt((n - 1) / stats.chi2.ppf(0.5 + LEVEL / 2, n - 1))
    hi = s3 * np.sqrt((n - 1) / stats.chi2.ppf(0.5 - LEVEL / 2, n - 1))
    return lo, hi


def bca_interval(
    stat: Callable[..., Any],
    strata: Sequence[np.ndarray],
    rng: np.random.Generator,
    n_boot: int = N_BOOT,
) -> Interval:
    """BCa bootstrap interval of `stat(*strata)`, resampling cycles within each stratum.

    `strata`: arrays with cycles on axis 0; `stat` takes one array per stratum with any
    leading batch axes before the cycle axis and returns the statistic per batch element.
    """
    strata = [np.asarray(s, np.float64) for s in strata]
    if any(s.shape[0] < 1 for s in strata) or sum(s.shape[0] for s in strata) < 3:
        return NAN_INTERVAL
    theta = float(stat(*strata))
    if not np.isfinite(theta):
        return NAN_INTERVAL
    boot = stat(*[s[rng.integers(0, s.shape[0], (n_boot, s.shape[0]))] for s in strata])
    boot = boot[np.isfinite(boot)]
    if boot.size < n_boot // 2 or np.ptp(boot) == 0:
        return NAN_INTERVAL if boot.size < n_boot // 2 else (theta, theta)
    p = (np.sum(boot < theta) + 0.5 * np.sum(boot == theta)) / boot.size
    z0 = special.ndtri(np.clip(p, 1.0 / (boot.size + 1), boot.size / (boot.size + 1)))
    # acceleration from the jackknife: leave one cycle out of one stratum at a time
    jack = []
    for k, s in enumerate(strata):
        n = s.shape[0]
        if n < 2:
            continue
        keep = np.flatnonzero(~np.eye(n, dtype=bool)).reshape(n, n - 1) % n
        args = [np.broadcast_to(o, (n, *o.shape)) for o in strata]
        args[k] = s[keep]
        jack.append(stat(*args))
    u = np.concatenate(jack) if jack else np.zeros(1)
    u = u[np.isfinite(u)]
    d = u.mean() - u
    den = 6.0 * np.sum(d**2) ** 1.5
    a = float(np.sum(d**3) / den) if den > 0 else 0.0
    z = special.ndtri(np.array([0.5 - LEVEL / 2, 0.5 + LEVEL / 2]))
    alpha = special.ndtr(z0 + (z0 + z) / (1.0 - a * (z0 + z)))
    lo, hi = np.quantile(boot, alpha)
    return float(lo), float(hi)


def fold_abs(lo: float, hi: float) -> Interval:
    """Interval of |d| from an interval [lo, hi] of d."""
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return NAN_INTERVAL
    if lo <= 0.0 <= hi:
        return 0.0, max(-lo, hi)
    return min(abs(lo), abs(hi)), max(abs(lo), abs(hi))


def pair(lo, hi) -> Interval:
    return float(lo), float(hi)


# batched statistics (cycles on axis −2 for points, −1 for scalars)


def rp_stat(x: np.ndarray) -> Any:
    """ISO 9283 RP = l̄ + 3·S_l of points `(…, n, 3)`."""
    l = np.linalg.norm(x - x.mean(axis=-2, keepdims=True), axis=-1)
    return l.mean(axis=-1) + 3.0 * np.std(l, axis=-1, ddof=1)


def mean_plus_3s(v: np.ndarray) -> Any:
    return v.mean(axis=-1) + 3.0 * np.std(v, axis=-1, ddof=1)


def aligned_mean_quaternion(q: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Mean unit quaternion of `(…, n, 4)` after aligning signs with `ref` `(4,)`: the
    chordal mean to second order in the scatter, batched."""
    s = np.where((q @ ref)[..., None] < 0, -q, q).sum(axis=-2)
    return s / np.linalg.norm(s, axis=-1, keepdims=True)


_UNITS = ("_mm_per_s", "_percent", "_mm", "_deg", "_s")


def with_intervals(
    rows: Sequence[tuple[str, float, float]], ci: dict[str, Interval], alias: dict[str, str]
) -> dict[str, float | list[float] | None]:
    """JSON entries ``{key: value·scale, key_ci95: [lo·scale, hi·scale] or None}`` from
    `(key with unit, value in SI, scale)` rows and SI intervals keyed by the key without
    its unit (or by `alias[that]`); None where no finite interval exists."""
    out: dict[str, float | list[float] | None] = {}
    for key, value, scale in rows:
        base = next((key[: -len(u)] for u in _UNITS if key.endswith(u)), key)
        lo, hi = ci.get(alias.get(base, base), NAN_INTERVAL)
        out[key] = float(value) * scale
        ok = np.isfinite(lo) and np.isfinite(hi)
        out[f"{key}_ci95"] = [float(lo) * scale, float(hi) * scale] if ok else None
    return out
