"""The σ a fit quotes (`quoted_sigma`): per parameter, the largest of the Gauss–Newton σ
and two that survive model error.

- **Gauss–Newton** ``s²H⁺`` (`covariance`): right when the residual is noise; it shrinks
  with every observation added, whatever the model misses.
- **Leave-one-block-out jackknife** (`robust_covariance`, `jackknife_covariance`): blocks
  that share a model error — regions of joint space for a pose-level fit of static
  poses, a bundle calibration's clusters (each dwell, each stretch of motion) for an LED
  recording — left out one at a time. It sees a model error that varies across the
  blocks, not one shared by all of them.
- **Model-error field** (`field_covariance`; from a calibration's clusters,
  `cluster_field`): the residual as a smooth random function of the joint angles, one
  variance per correlation length; it also covers the error correlated across the whole
  workspace, which biases the estimate alike in every block.

Each source is an estimate with its own sampling error and its own blind spot; the
largest guards against the one that errs low. Entries under a prior (a map's knots) quote
Gauss–Newton alone: leaving out the data near a knot leaves it to its prior, which the
jackknife and the field would measure instead of the estimate.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Bool, Float

#: the sources of a quoted σ; a tie goes to the first
SOURCES = ("gauss_newton", "jackknife", "field")


@dataclasses.dataclass(frozen=True)
class QuotedSigma:
    """The σ quoted per parameter and the source that set each.

    `sigma` `(p,)`: the largest of the sources' σ (NaN where none has one); `source`
    `(p,)`: index into `SOURCES` of the source that set it (−1 where NaN); `parts`: each
    source's σ `(p,)` by name (NaN where not computed). Units: those of the parameters.
    """

    sigma: np.ndarray
    source: np.ndarray
    parts: dict[str, np.ndarray]

    def share(self) -> dict[str, float]:
        """Fraction of the parameters with a σ that each source set."""
        n = max(1, int(np.sum(self.source >= 0)))
        return {s: float(np.sum(self.source == k)) / n for k, s in enumerate(SOURCES)}


def sigma_of(
    covariance: Float[np.ndarray, "p p"] | None, free: Bool[np.ndarray, " p"] | None = None
) -> Float[np.ndarray, " p"] | None:
    """σ on the diagonal of `covariance` (rounding below zero clipped), NaN outside `free`
    (default: every entry); None for None."""
    if covariance is None:
        return None
    sig = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    return sig if free is None else np.where(free, sig, np.nan)


def quoted_sigma(
    gauss_newton: Float[np.ndarray, " p"],
    jackknife: Float[np.ndarray, " p"] | None = None,
    field: Float[np.ndarray, " p"] | None = None,
    *,
    prior: Bool[np.ndarray, " p"] | None = None,
) -> QuotedSigma:
    """The quoted σ: per parameter the largest of `gauss_newton`, `jackknife` and `field`
    (each `(p,)`, NaN where that source has none; None: not computed), Gauss–Newton alone
    on the entries under a `prior`."""
    gn = np.asarray(gauss_newton, float)
    parts = {"gauss_newton": gn}
    for name, s in (("jackknife", jackknife), ("field", field)):
        s = np.full(gn.shape, np.nan) if s is None else np.asarray(s, float)
        parts[name] = s if prior is None else np.where(prior, np.nan, s)
    stack = np.stack([parts[s] for s in SOURCES])
    known = ~np.isnan(stack)
    source = np.where(known.any(0), np.argmax(np.where(known, stack, -np.inf), 0), -1)
    sigma = np.where(
        source >= 0, np.take_along_axis(stack, np.maximum(source, 0)[None], 0)[0], np.nan
    )
    return QuotedSigma(sigma=sigma, source=source, parts=parts)
