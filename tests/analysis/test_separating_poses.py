"""The T-optimal choice of poses that tell two models apart (`_separating_poses._greedy`):
its criterion against a direct least-squares refit of the rival, and each choice the
best next one by exhaustive search."""

import numpy as np

from robtraj.analysis._separating_poses import _greedy


def _refit_chi2(d, w, jac, info, chosen) -> float:
    """What the rival cannot fit at the `chosen` candidates after changing its parameters
    δ, held to the recording's information `info`: min over δ of
    Σ_k (d_k − J_k δ)ᵀ W_k (d_k − J_k δ) + δᵀ info δ, by `np.linalg.lstsq` on the stacked
    system (√info from its Cholesky factor)."""
    rows = [np.sqrt(w[k])[:, None] * jac[k] for k in chosen]
    rhs = [np.sqrt(w[k]) * d[k] for k in chosen]
    lower = np.linalg.cholesky(info)
    a = np.vstack([*rows, lower.T])
    b = np.concatenate([*rhs, np.zeros(info.shape[0])])
    delta = np.linalg.lstsq(a, b, rcond=None)[0]
    return float(np.sum((a @ delta - b) ** 2))


def test_the_criterion_is_the_rivals_refitted_chi2_and_the_greedy_order_is_sound():
    rng = np.random.default_rng(2)
    k, r, p = 12, 15, 3
    d = rng.normal(size=(k, r))
    w = rng.uniform(0.5, 2.0, (k, r))
    jac = rng.normal(size=(k, r, p))
    m = rng.normal(size=(p, p))
    info = m @ m.T + 0.5 * np.eye(p)
    q = rng.normal(size=(k, 6))
    chosen, gains = _greedy(d, w, jac, info, q, 4)
    assert len(set(chosen.tolist())) == 4
    # the gains add up to the rival's χ² after refitting on the chosen poses
    for n in range(1, 5):
        np.testing.assert_allclose(
            gains[:n].sum(), _refit_chi2(d, w, jac, info, chosen[:n]), rtol=1e-9
        )
    # each is the best next pose given those before it (exhaustive over the rest)
    for n in range(4):
        rest = [i for i in range(k) if i not in chosen[:n]]
        after = [_refit_chi2(d, w, jac, info, [*chosen[:n], i]) for i in rest]
        assert chosen[n] == rest[int(np.argmax(after))]
