"""Zero-mean Gaussian priors on parameters, as the engine's normal equations take them.

A term of the dictionary may carry the precision matrix Λ of a prior on its
coefficients (`robtraj.model.Term.precision`). A fit that estimates the term minimises
``Σ w r² + cᵀΛc`` (c the coefficients' values): the normal function of the problem adds
``H += Λ``, ``b −= Λc``, ``cost += cᵀΛc`` (the negative log-posterior up to a constant;
`robtraj.estimate.solve`'s sign convention, ``b = −½∇cost``). The prior is data of the
normal function (`GaussianPrior`), so that the function stays pure and fits that differ
only in the prior's values share one compilation. Directions the prior regularises are
determined (`identifiability` sees the posterior H) and the covariance is the posterior
one.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import scipy.linalg
from jaxtyping import Array, Float, Int

from ..model import term


class GaussianPrior(eqx.Module):
    """A zero-mean Gaussian prior on the θ entries `index` `(k,)` with precision
    `precision` `(k, k)` [1/unit²] (block diagonal when it holds several terms)."""

    index: Int[Array, " k"]
    precision: Float[Array, "k k"]

    @property
    def size(self) -> int:
        return int(self.index.shape[0])

    def add_to(self, h, b, cost, values: Float[Array, " k"]):
        """``(H + Λ, b − Λc, cost + cᵀΛc)`` for the entries' values `c` (`values`)."""
        if self.size == 0:
            return h, b, cost
        lc = self.precision @ values
        ix = self.index
        h = h.at[ix[:, None], ix[None, :]].add(self.precision)
        return h, b.at[ix].add(-lc), cost + values @ lc

    def cost(self, values) -> Float[Array, ""]:
        """``cᵀΛc``."""
        return values @ (self.precision @ values) if self.size else jnp.zeros(())

    def dense(self, p: int) -> np.ndarray:
        """Λ as a `(p, p)` matrix over all of θ (zero outside `index`)."""
        out = np.zeros((p, p))
        ix = np.asarray(self.index)
        out[np.ix_(ix, ix)] = np.asarray(self.precision)
        return out


def no_prior() -> GaussianPrior:
    return GaussianPrior(jnp.zeros(0, jnp.int32), jnp.zeros((0, 0)))


def term_prior(
    blocks: Sequence[tuple[str, int]], precisions: dict[str, np.ndarray] | None = None
) -> GaussianPrior:
    """The prior of the terms among `blocks` ``[(effect name, first θ entry)]`` that have
    one: each term's `Term.precision`, or `precisions[name]` where given (e.g. the
    hyper-parameters a cross-validation chose)."""
    precisions = precisions or {}
    index, mats = [], []
    for name, start in blocks:
        t = term(name)
        lam = precisions.get(name, None if t is None else t.precision)
        if lam is None:
            continue
        lam = np.asarray(lam, float)
        index.append(np.arange(start, start + lam.shape[0]))
        mats.append(lam)
    if not mats:
        return no_prior()
    return GaussianPrior(
        jnp.asarray(np.concatenate(index), jnp.int32), jnp.asarray(scipy.linalg.block_diag(*mats))
    )
