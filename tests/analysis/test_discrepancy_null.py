"""Discrepancy discovery when the library has nothing to name: no hidden effect (false
positives over 20 seeds) and an effect outside the library (reported as unexplained)."""

import numpy as np
from test_discrepancy import _hidden

from robtraj.analysis.discrepancy import discover


def test_nothing_hidden_nothing_named_over_20_seeds():
    named = [discover(_hidden({}, seed=s)[0]).named for s in range(20)]
    false_positive = sum(bool(n) for n in named) / len(named)
    assert false_positive <= 0.05, named


def test_an_effect_outside_the_library_is_reported_as_unexplained_with_its_joint():
    rec, _ = _hidden({}, seed=3)
    q = rec.robot.joints.copy()
    # the encoder of joint 2 has a periodic error: the logged angle is off by A·sin(4·q2)
    q[:, 1] -= 4e-4 * np.sin(4 * q[:, 1])
    rec = rec.replace(robot=rec.robot.__class__(rec.robot.time, q, rec.robot.model, rec.robot.dh))
    res = discover(rec)
    assert res.unexplained
    assert "joint 2" in res.unexplained_where[:3], res.unexplained_where
