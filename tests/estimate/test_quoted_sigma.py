"""The quoted σ (`quoted_sigma`): per parameter the largest of Gauss–Newton, the
jackknife and the model-error field, and the source named; on simulated LED calibrations
with a smooth joint-angle error the fitted model does not contain, its coverage of the
truth."""

import numpy as np
import pytest
import scipy.stats

from robtraj.estimate import SIGMA_SOURCES, quoted_sigma
from robtraj.estimate.calibration import error_against, fit
from robtraj.sim import calibration_twin

#: the spread of a seed's coverage over its ~66 parameters is that of ~22 independent
#: ones (40 seeds of the exhaustive twin: SD 4.5 % per seed against 2.7 % binomial):
#: one model error biases many parameters of a seed alike
DESIGN_EFFECT = 3.0


def test_the_largest_source_is_quoted_and_named():
    gn = np.array([1.0, 2.0, np.nan, 1.0, 3.0, 2.0])
    jk = np.array([2.0, 1.0, np.nan, np.nan, 1.0, 2.0])
    field = np.array([0.5, 4.0, np.nan, 2.0, 5.0, 1.0])
    prior = np.array([False, False, False, False, True, False])
    q = quoted_sigma(gn, jk, field, prior=prior)
    np.testing.assert_array_equal(q.sigma, [2.0, 4.0, np.nan, 2.0, 3.0, 2.0])
    # a tie goes to the first source; the entry under a prior quotes Gauss–Newton alone
    names = [SIGMA_SOURCES[k] if k >= 0 else None for k in q.source]
    assert names == ["jackknife", "field", None, "field", "gauss_newton", "gauss_newton"]
    assert q.share() == {"gauss_newton": 0.4, "jackknife": 0.2, "field": 0.4}
    alone = quoted_sigma(gn)
    np.testing.assert_array_equal(alone.sigma, gn)
    assert np.all(np.isnan(alone.parts["field"]))


def _covered(seed: int, duration: float) -> dict[str, np.ndarray]:
    """Per estimated rigid-transform and constellation parameter of a fit of `calibration_twin` (joint-angle error on every joint, 1–3 cycles per
    turn of (0.5–1)·100/c µrad, random phase; 0.04–0.18 mm RMS at the flange):
    whether each source's σ and the quoted one cover the truth at 95 %
    (|estimate − truth| ≤ 1.96 σ), and the σ."""
    rec = calibration_twin(seed, duration)
    res = fit(rec)
    err = error_against(res, rec.truth, rec.tool.led_ids)
    q = res.quoted
    assert len(res.parameter_names) == err.size  # rigid transforms and constellation only
    ok = q.parts["gauss_newton"] > 0  # LEDs never seen are not estimated
    out = {k: np.abs(err[ok]) <= 1.96 * s[ok] for k, s in q.parts.items()}
    out["quoted"] = np.abs(err[ok]) <= 1.96 * q.sigma[ok]
    out["sigma"] = q.sigma[ok]
    out["parts"] = {k: s[ok] for k, s in q.parts.items()}
    out["field_found"] = any(k > 0 for k in res.model_error.get("ratios", []))
    return out


@pytest.fixture(scope="module")
def small_twin():
    return [_covered(seed, 24.0) for seed in range(3)]


def test_the_quoted_sigma_covers_a_twin_with_model_error(small_twin):
    """Three 24 s runs (~190 parameters): the quoted σ is at least each source's, the
    field is found, and the coverage is not grossly low. The bound: with honest 95 %
    σ, the number covered is binomial over ~190 / `DESIGN_EFFECT` independent
    parameters; its 0.1 % point (``binom.ppf(0.001, n, 0.95) / n``, 0.84) is failed
    with probability < 0.001. Gauss–Newton alone covers far less (59 %)."""
    for run in small_twin:
        for s in run["parts"].values():
            assert np.all(np.isnan(s) | (run["sigma"] >= s))
        assert run["field_found"]
    quoted = np.concatenate([r["quoted"] for r in small_twin])
    n = int(quoted.size / DESIGN_EFFECT)
    bound = scipy.stats.binom.ppf(0.001, n, 0.95) / n
    assert quoted.mean() >= bound, (quoted.mean(), bound)
    gauss_newton = np.concatenate([r["gauss_newton"] for r in small_twin])
    assert gauss_newton.mean() < 0.85, gauss_newton.mean()


@pytest.mark.exhaustive
def test_the_quoted_sigma_covers_the_truth_in_95_percent_over_40_seeds():
    """40 runs of 40 s (15 dwells, ~130 clusters, ~2 640 parameters): the quoted σ cover
    the truth in 92–98 %. With honest σ the covered share is binomial over
    ~2 640 / `DESIGN_EFFECT` ≈ 880 independent parameters, SD 0.73 %: ±3 % is ±4 SD,
    which honest σ fail with probability < 1e-4; σ that cover 91 % or 99 % fail it
    almost surely. Measured 97 % (rigid transforms 93 %, constellation 98 %); the σ
    quoted before the field (the larger of Gauss–Newton and the cluster jackknife)
    cover 69 %, Gauss–Newton alone 57 %."""
    runs = [_covered(seed, 40.0) for seed in range(40)]
    quoted = np.concatenate([r["quoted"] for r in runs])
    assert 0.92 <= quoted.mean() <= 0.98, quoted.mean()
