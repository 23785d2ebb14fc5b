"""Discrepancy discovery on recordings with hidden effects (truth stripped).

All recordings share one shape (calibration scenario, 24 s at 25 Hz) so that the fits
compile once per set of effects. The full matrix (every effect at a realistic and at a
small magnitude, two effects together) is marked `exhaustive` and run on demand:
``pytest -m exhaustive tests/analysis/test_discrepancy.py``.
"""

import numpy as np
import pytest

from robtraj.analysis.discrepancy import discover
from robtraj.sim import simulate


def _hidden(effects, seed=1):
    rec = simulate("calibration", seed=seed, duration=24.0, rate=25.0, effects=effects)
    return rec.replace(truth=None), rec.truth


def _check_named(res, effects, hidden_values):
    assert res.named[: len(effects)] and set(res.named) == set(effects), res.named
    for step in res.steps:
        truth = np.broadcast_to(
            np.asarray(hidden_values[step.effect], float), np.shape(hidden_values[step.effect])
        )
        for name, (value, sigma) in step.parameters.items():
            idx = name[len(step.effect) :]
            want = (
                float(eval(f"truth{idx.replace('.d', '[0]').replace('.a', '[1]')}"))
                if idx
                else float(truth)
            )
            assert abs(value - want) < 3 * sigma + 1e-12, (name, value, want, sigma)
    # the gap shrinks to the noise floor: what is left is below a tenth of the noise
    assert res.gap_after_m < 0.1 * res.noise_sigma_m, (res.gap_after_m, res.noise_sigma_m)
    assert not res.unexplained, res.structure


# realistic magnitudes: a few tenths of a millimetre at the TCP
REALISTIC = {
    "time_offset": 0.004,
    "joint_offset": [0.0, 3e-4, -2e-4, 0.0, 3e-4, 0.0],
    "link_length": [[0, 3e-4], [0, -3e-4], [0, 0], [3e-4, 0], [0, 0], [0, 0]],
    "joint_compliance": 1.5e-6,
    "backlash": [0.0, 2e-4, 2e-4, 0.0, 0.0, 0.0],
    "led_angle_bias": 200e-6,
    "tracker_scale": 1e-4,
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


@pytest.mark.exhaustive
@pytest.mark.parametrize("scale", [1.0, "small"])
@pytest.mark.parametrize("effect", list(REALISTIC))
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
