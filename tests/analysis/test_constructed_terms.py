"""Constructed terms: a joint angle error built from the recording's signals, named by
its definition, screened on the fit's moments, and found by the discrepancy search when
no library effect, dictionary term or map explains the structure (one form in CI,
`test_discrepancy_null.py::test_a_cross_joint_product_is_named_as_a_constructed_term`,
next to the same recording searched without them; every form over 10 seeds on demand:
``pytest -m exhaustive tests/analysis/test_constructed_terms.py``)."""

import jax.numpy as jnp
import numpy as np
import pytest
from test_discrepancy import _hidden

from robtraj.analysis._constructed_terms import _statistics
from robtraj.analysis._localisation import moments
from robtraj.analysis.discrepancy import discover
from robtraj.model import Effects, is_effect, term
from robtraj.model._constructed import Factor, candidate_groups, features, parse
from robtraj.model._dictionary import joint_term_error


def test_a_constructed_term_is_built_from_its_name():
    """The name is the definition: its features are the products of its factors' basis
    functions (against the formulas written out), it moves the joint it names, and an
    Effects holding it goes through a dict (CALIB.json) and back."""
    rng = np.random.default_rng(0)
    q, tau = rng.uniform(-3, 3, 6), rng.uniform(-50, 50, 6)
    t = term("joint2_by_q3h3_q4h1")
    assert t.joint == 1 and t.size == 4 and t.unit == "rad"
    want = [
        np.sin(3 * q[2]) * np.sin(q[3]),
        np.sin(3 * q[2]) * np.cos(q[3]),
        np.cos(3 * q[2]) * np.sin(q[3]),
        np.cos(3 * q[2]) * np.cos(q[3]),
    ]
    np.testing.assert_allclose(np.asarray(t.fn(q, np.zeros(6), tau)), want, rtol=1e-12)
    lin = term("joint3_by_q2_tau5")
    assert lin.components == ("q2_tau5",) and lin.unit == "rad/(rad·N·m)"
    err = np.asarray(
        joint_term_error(
            {lin.name: jnp.array([2e-6])}, jnp.asarray(q), jnp.zeros(6), jnp.asarray(tau)
        )
    )
    np.testing.assert_allclose(err, np.eye(6)[2] * 2e-6 * q[1] * tau[4], rtol=1e-12)
    # not constructed terms: a factor twice, an unknown signal, no joint 0
    for bad in ("joint2_by_q2_q2", "joint2_by_x3", "joint0_by_q1", "joint2_by_q3h1_q3h2"):
        assert term(bad) is None and not is_effect(bad), bad
    eff = Effects.zeros(6, (t.name,)).with_value(t.name, [1e-4, 0.0, -6e-4, 2e-5])
    back = Effects.from_dict(eff.to_dict())
    np.testing.assert_array_equal(np.asarray(back.terms[t.name]), [1e-4, 0.0, -6e-4, 2e-5])
    # the screen's candidates leave out what the dictionary and the library hold
    names = {parse_name for parse_name in (_name(j, f) for j, f in candidate_groups(6))}
    assert "joint2_by_q2h1" not in names and "joint2_by_tau2" not in names
    assert {"joint2_by_q3h3_q4h1", "joint2_by_q2", "joint3_by_q2_tau5"} <= names
    assert all(parse(n) is not None for n in names)


def _name(j, factors):
    from robtraj.model._constructed import name_of

    return name_of(j, factors)


def test_the_screen_statistic_is_the_chi2_decrease_of_a_direct_refit():
    """The screen's statistic of a term equals the weighted least-squares χ² decrease of
    adding its columns to the nuisance and every joint's constant offset, computed on
    the stacked observations by `numpy.linalg.lstsq`."""
    rng = np.random.default_rng(1)
    units, leds, joints, g = 300, 4, 3, 5
    residual = rng.normal(size=(units, leds, 3)) * 1e-4
    residual[rng.random((units, leds)) < 0.2] = np.nan
    weight = rng.uniform(0.5, 2.0, (units, leds)) * 1e8
    var3 = np.full((units, leds), 3e-8)
    channels = rng.normal(size=(units, leds, 3, 3 + joints))
    nuisance = rng.normal(size=(units, leds, 3, g))
    block = np.arange(units) * 8 // units
    mom = moments(residual, weight, var3, channels, nuisance, block, 8)
    q, tau = rng.uniform(-2, 2, (units, joints)), rng.uniform(-40, 40, (units, joints))
    group = (1, (Factor("q", 0, 2), Factor("tau", 2)))
    ((stat, rank),) = _statistics(mom, [group], q, tau)

    phi = features(group[1], q, tau, np)  # (U, k)
    use = np.isfinite(residual[..., 0])
    sw = np.sqrt(np.repeat(np.where(use, weight, 0.0), 3, 1)).reshape(-1)
    r = np.where(use[..., None], residual, 0.0).reshape(-1)
    base = np.concatenate([nuisance, channels[..., 3:]], -1).reshape(-1, g + joints)
    term_cols = (channels[..., 3 + group[0], None] * phi[:, None, None, :]).reshape(-1, 2)

    def chi2(a):
        x, *_ = np.linalg.lstsq(a * sw[:, None], r * sw, rcond=None)
        return float(np.sum((sw * (r - a @ x)) ** 2))

    want = chi2(base) - chi2(np.concatenate([base, term_cols], 1))
    assert rank == 2
    np.testing.assert_allclose(stat, want, rtol=1e-8)


def _torque(rec, joint):
    """Gravity torque [N·m] of `joint` (0-based) at each logged configuration."""
    import jax

    from robtraj.model import gravity_torque, robot_from_log

    robot = robot_from_log(rec.robot)
    q = jnp.asarray(rec.robot.joints)
    return np.asarray(jax.vmap(lambda a: gravity_torque(robot, a))(q))[:, joint]


def _logged_off(rec, joint, error):
    """`rec` whose controller logs joint `joint`'s (0-based) angle off by `error(rec)`
    [rad] (the tracker sees the true arm)."""
    q = rec.robot.joints.copy()
    q[:, joint] -= error(rec)
    return rec.replace(robot=rec.robot.__class__(rec.robot.time, q, rec.robot.model, rec.robot.dh))


# hidden effects no dictionary entry matches, 0.1–0.5 mm at the tool over the calibration
# scenario: (the error, the joint it is on, the term that names it)
FORMS = {
    "cross_joint_linear": (lambda r: 8e-4 * r.robot.joints[:, 3], 2, "joint3_by_q4"),
    "cross_joint_harmonic": (lambda r: 4e-4 * np.sin(2 * r.robot.joints[:, 5]), 1,
                             "joint2_by_q6h2"),
    "product_of_two_angles": (
        lambda r: 6e-4 * np.cos(3 * r.robot.joints[:, 2]) * np.sin(r.robot.joints[:, 3]),
        1,
        "joint2_by_q3h3_q4h1",
    ),
    "torque_driven_other_joint": (lambda r: 3e-6 * _torque(r, 1), 2, "joint3_by_tau2"),
}  # fmt: skip


#: forms the search does not yet name, with why
_NOT_YET = {
    "torque_driven_other_joint": "at this size the library's compliance and link lengths "
    "absorb it to the floor before constructed terms are offered (seed 0: gap 72 → 12 µm, "
    "floor 18 µm)",
}


@pytest.mark.exhaustive
@pytest.mark.parametrize(
    "form",
    [
        pytest.param(f, marks=pytest.mark.xfail(reason=_NOT_YET[f], strict=False))
        if f in _NOT_YET
        else f
        for f in sorted(FORMS)
    ],
)
def test_hidden_effects_outside_the_dictionary_are_named_as_constructed_terms(form):
    """Each form over 10 seeds: named alone as the term of the right variables and form
    with the gap below 1.2× its floor in ≥ 9 (a failure rate up to 10 % allowed)."""
    error, joint, want = FORMS[form]
    ok = []
    for seed in range(10):
        res = discover(_logged_off(_hidden({}, seed=seed)[0], joint, error), max_steps=2)
        ok.append(res.named == [want] and res.gap_after_m <= 1.2 * res.gap_floor_m)
    assert sum(ok) >= 9, ok
