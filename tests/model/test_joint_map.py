"""Joint angle error maps (``joint{j}_map``): hat features, prior and words against
direct numpy formulas, and the maps in the one forward model."""

import jax.numpy as jnp
import numpy as np
import pytest

from robtraj._errors import UserError
from robtraj.model import (
    MAP_KNOTS,
    Effects,
    _joint_map as jm,
    abb_irb2400_16,
    dictionary,
    effective_joints,
    is_effect,
    joint_maps,
    known_effects,
    map_active,
    map_precision,
    map_summary,
    map_support,
    map_values,
    map_words,
    parse_effect,
    register_effect,
    term,
    unregister_effect,
)


def _hat_reference(q, n):
    """Every hat feature by the definition: 1 − |q − knot|/h on the nearest turn, ≥ 0."""
    h = 2 * np.pi / n
    out = np.zeros((q.size, n))
    for i, a in enumerate(q):
        for k in range(n):
            d = (a - k * h) % (2 * np.pi)
            d = min(d, 2 * np.pi - d)
            out[i, k] = max(0.0, 1.0 - d / h)
    return out


@pytest.mark.parametrize("n", [7, MAP_KNOTS])
def test_hat_features_match_their_definition(n):
    rng = np.random.default_rng(0)
    h = 2 * np.pi / n
    # inside, on knots, at ±π, beyond a turn and negative
    q = np.concatenate([rng.uniform(-9, 9, 40), [0.0, h, -h, np.pi, -np.pi, 2 * np.pi - 1e-12]])
    ref = _hat_reference(q, n)
    dense = np.asarray(jm.features(jnp.asarray(q), n))
    np.testing.assert_allclose(dense, ref, atol=1e-12)
    # two active knots carry every feature, and they sum to one (partition of unity)
    idx, w = map_active(q, n)
    sparse = np.zeros_like(ref)
    for a in range(2):
        np.add.at(sparse, (np.arange(q.size), idx[:, a]), w[:, a])
    np.testing.assert_allclose(sparse, ref, atol=1e-12)
    np.testing.assert_allclose(w.sum(1), 1.0)
    # the JAX path gives the same knots and values
    idx_j, w_j = map_active(jnp.asarray(q), n)
    np.testing.assert_array_equal(np.asarray(idx_j), idx)
    np.testing.assert_allclose(np.asarray(w_j), w, atol=1e-12)
    c = rng.normal(size=n)
    np.testing.assert_allclose(map_values(c, q), ref @ c, atol=1e-12)


def test_a_map_interpolates_its_knots_and_is_periodic():
    c = np.random.default_rng(1).normal(size=MAP_KNOTS)
    k = jm.knots()
    np.testing.assert_allclose(map_values(c, k), c, atol=1e-12)
    np.testing.assert_allclose(map_values(c, k + 2 * np.pi), c, atol=1e-12)
    np.testing.assert_allclose(map_values(c, k - 6 * np.pi), c, atol=1e-12)
    mid = 0.5 * (k + np.roll(k, -1) + 2 * np.pi * (np.arange(MAP_KNOTS) == MAP_KNOTS - 1))
    np.testing.assert_allclose(map_values(c, mid), 0.5 * (c + np.roll(c, -1)), atol=1e-12)


def test_prior_precision_is_the_stated_quadratic_form():
    n, sf, ell = 50, 2e-3, 0.3
    lam = map_precision(n, sf, ell)
    h = 2 * np.pi / n
    c = np.random.default_rng(2).normal(size=n)
    want = np.sum(c**2) / sf**2 + ell**2 / (2 * sf**2) * np.sum(((np.roll(c, -1) - c) / h) ** 2)
    np.testing.assert_allclose(c @ lam @ c, want, rtol=1e-12)
    assert np.allclose(lam, lam.T) and np.linalg.eigvalsh(lam).min() > 0
    # the smallest eigenvalue is the constant map's: 1/σ_f²
    np.testing.assert_allclose(np.linalg.eigvalsh(lam).min(), 1 / sf**2, rtol=1e-10)
    np.testing.assert_allclose(term("joint3_map").precision, map_precision())


def test_support_is_the_knots_near_the_data():
    q = np.array([0.01, 0.02, 3.0])
    s = map_support(q, margin=0)
    assert sorted(np.flatnonzero(s)) == sorted(set(map_active(q)[0].ravel()))
    wide = map_support(q, margin=2)
    assert wide.sum() == s.sum() + 2 * 2 * 2  # two separate groups, two knots each side


def test_maps_act_in_the_forward_model_through_their_joint():
    robot = abb_irb2400_16()
    q = jnp.array([0.3, -0.2, 0.5, 1.1, -0.7, 0.4])
    c = np.random.default_rng(3).normal(0, 1e-4, MAP_KNOTS)
    eff = Effects.from_dict({"joint2_map": c.tolist(), "joint5_map": 2e-4})
    out = np.asarray(effective_joints(robot, eff, q, jnp.zeros(6)))
    want = np.asarray(q).copy()
    want[1] += map_values(c, -0.2)
    want[4] += 2e-4  # a constant map is a joint offset
    np.testing.assert_allclose(out, want, atol=1e-15)


def test_maps_are_known_terms_but_not_default_candidates():
    assert joint_maps(6) == tuple(f"joint{j}_map" for j in range(1, 7))
    assert all(is_effect(m) for m in joint_maps(6))
    assert set(joint_maps(6)) <= set(known_effects())
    assert not set(joint_maps(9)) & set(dictionary(9))
    t = term("joint2_map")
    assert t.size == MAP_KNOTS and t.kind == "joint" and t.joint == 1 and not t.searched
    name, v = parse_effect("joint2_map=1e-4")
    assert name == "joint2_map" and v.shape == (MAP_KNOTS,) and np.all(v == 1e-4)
    with pytest.raises(UserError, match="takes 1 or 256 values"):
        parse_effect("joint2_map=1,2")
    eff = Effects.from_dict({"joint4_map": np.linspace(0, 1e-4, MAP_KNOTS).tolist()})
    assert Effects.from_dict(eff.to_dict()).to_dict() == eff.to_dict()


def test_a_registered_term_may_carry_a_prior():
    lam = np.diag([1e8, 4e8])
    t = register_effect(
        "joint2_two_cos",
        lambda q, s, tau: jnp.stack([jnp.cos(q[1]), jnp.cos(2 * q[1])]),
        ("c1", "c2"),
        joint=2,
        precision=lam,
    )
    try:
        np.testing.assert_array_equal(t.precision, lam)
        with pytest.raises(UserError, match="symmetric 2×2"):
            register_effect(
                "bad_prior", lambda q, s, tau: q[:2], ("a", "b"), joint=1, precision=np.eye(3)
            )
    finally:
        unregister_effect("joint2_two_cos")


def test_a_map_in_words():
    k = jm.knots()
    c = 3e-4 * np.sin(17 * k + 0.4) + 1e-4
    s = map_summary(c, (-2.4, 0.1))
    assert round(s["cycles_per_rev"]) == 17
    inside = ((k - (-2.4)) % (2 * np.pi)) <= 2.5
    np.testing.assert_allclose(s["rms_rad"], np.sqrt(np.mean(c[inside] ** 2)), rtol=0.05)
    words = map_words(2, c, (-2.4, 0.1))
    assert words.startswith("joint 2 angle error map: rms 0.2")
    assert "strongest at 17 cycles/rev" in words and "q2 ∈ [−2.40, 0.10] rad" in words
    # a range beyond ±π (a joint that turned past it) still holds its knots
    assert map_summary(c, (-4.27, 0.06))["peak_rad"] == pytest.approx(4e-4, rel=0.02)
