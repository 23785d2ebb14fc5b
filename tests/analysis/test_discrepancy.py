"""Discrepancy discovery on recordings with hidden effects (truth stripped).

All recordings share one shape (calibration scenario, 24 s at 25 Hz) so that the fits
compile once per set of effects. One effect per family runs in CI; the full matrix (every
effect at a realistic and at a small magnitude, two effects together) is marked
`exhaustive` and run on demand:
``pytest -m exhaustive tests/analysis/test_discrepancy.py``.
"""

import numpy as np
import pytest

from robtraj.analysis.discrepancy import discover
from robtraj.model import Effects
from robtraj.sim import simulate


def _hidden(effects, seed=1):
    rec = simulate("calibration", seed=seed, duration=24.0, rate=25.0, effects=effects)
    return rec.replace(truth=None), rec.truth


def _check_named(res, effects, hidden_values):
    assert res.named[: len(effects)] and set(res.named) == set(effects), res.named
    for step in res.steps:
        # a scalar for a per-joint effect fills every joint, as in the simulator
        truth = np.asarray(
            getattr(
                Effects.zeros(6).with_value(step.effect, hidden_values[step.effect]), step.effect
            )
        )
        for name, (value, sigma) in step.parameters.items():
            idx = name[len(step.effect) :]
            want = (
                float(eval(f"truth{idx.replace('.d', '[0]').replace('.a', '[1]')}"))
                if idx
                else float(truth)
            )
            assert abs(value - want) < 3 * sigma + 1e-12, (name, value, want, sigma)
    # the gap shrinks to the noise floor: what is left is what a complete model leaves by
    # chance (two standard errors of the gap's estimate; its calibration is tested below)
    assert res.gap_after_m <= res.gap_floor_m, (res.gap_after_m, res.gap_floor_m)
    assert not res.unexplained, res.structure


def test_gap_floor_is_two_standard_errors_of_the_gap_of_pure_noise():
    """With residuals of pure noise and σ̂ estimated from static samples, the gap exceeds
    its floor (2 standard errors of gap²) in ~2.3 % of trials and floor/√2 (1 standard
    error) in ~16 % — a floor neither vacuous nor loose."""
    from types import SimpleNamespace

    from robtraj.analysis._residual_stats import gap as _gap, gap_floor as _gap_floor

    rng = np.random.default_rng(0)
    sigma, trials = 40e-6, 400
    above = np.zeros((trials, 2), bool)
    for t in range(trials):
        r = rng.normal(0.0, sigma, (300, 10, 3))
        dev2 = np.mean(rng.normal(0.0, sigma, (4000, 3)) ** 2, -1)  # static, per axis
        var3 = np.full(r.shape[:2], 3 * dev2.mean())
        rel_se = dev2.std() / np.sqrt(dev2.size) / dev2.mean()
        res = SimpleNamespace(residuals=r)
        gap, floor = _gap(res, var3), _gap_floor(res, var3, rel_se)
        above[t] = gap > floor, gap > floor / np.sqrt(2)
    p2, p1 = above.mean(0)
    # binomial standard errors at n = 400: 0.75 % and 1.8 %
    assert 0.003 < p2 < 0.05, p2
    assert 0.10 < p1 < 0.23, p1


# realistic magnitudes: a few tenths of a millimetre at the TCP
REALISTIC = {
    "time_offset": 0.004,
    "joint_offset": [0.0, 3e-4, -2e-4, 0.0, 3e-4, 0.0],
    "link_length": [[0, 3e-4], [0, -3e-4], [0, 0], [3e-4, 0], [0, 0], [0, 0]],
    "joint_compliance": 1.5e-6,
    "backlash": [0.0, 2e-4, 2e-4, 0.0, 0.0, 0.0],
    "led_angle_bias": 200e-6,
    # a scale is mostly absorbed by camera←base and the constellation: 1e-4 leaves a gap of
    # 8 µm on these 24 s, below its floor (23 µm), and is rightly not named
    "tracker_scale": 5e-4,
    "thermal_drift": [1e-4, 0.0, -1e-4],
}


def test_hidden_compliance_is_named_with_its_value_and_the_gap_closes():
    effects = {"joint_compliance": REALISTIC["joint_compliance"]}
    rec, truth = _hidden(effects)
    res = discover(rec)
    assert res.gap_before_m > 10 * res.gap_after_m
    _check_named(res, ["joint_compliance"], {"joint_compliance": np.full(6, 1.5e-6)})
    doc = res.to_json()
    assert set(doc) >= {"gap_before_m", "steps", "gap_after_m", "unexplained"}
    assert doc["steps"][0]["effect"] == "joint_compliance"


# one effect per family runs in CI (clock, joint geometry, tracker, LED; the joint
# non-geometric family is the compliance test above); the rest of the matrix on demand
CI_FAMILIES = ("time_offset", "link_length", "tracker_scale", "led_angle_bias")


@pytest.mark.parametrize(
    "effect, scale",
    [
        pytest.param(e, s, marks=() if (s == 1.0 and e in CI_FAMILIES) else pytest.mark.exhaustive)
        for s in (1.0, "small")
        for e in REALISTIC
    ],
)
def test_every_effect_is_named(effect, scale):
    value = np.asarray(REALISTIC[effect], float)
    rec, _ = _hidden({effect: value})
    if scale == "small":  # about 3× the noise floor at the TCP
        probe = discover(rec, candidates=(effect,))
        value = value * 3 * probe.noise_sigma_m / max(probe.gap_before_m, 1e-12)
        rec, _ = _hidden({effect: value})
    res = discover(rec)
    _check_named(res, [effect], {effect: value})


@pytest.mark.exhaustive
def test_two_hidden_effects_are_both_named():
    effects = {"time_offset": 0.003, "joint_compliance": 1.5e-6}
    rec, _ = _hidden(effects, seed=4)
    res = discover(rec)
    _check_named(res, list(effects), {"time_offset": 0.003, "joint_compliance": np.full(6, 1.5e-6)})
