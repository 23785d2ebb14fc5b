"""The dictionary's terms in the one forward model, against direct numpy formulas."""

import jax.numpy as jnp
import numpy as np
import pytest

from robtraj._errors import UserError
from robtraj.model import (
    Effects,
    abb_irb2400_16,
    default_terms,
    describe,
    dictionary,
    effect_component_names,
    effective_joints,
    gravity_torque,
    hemispherical_tool,
    joint_maps,
    led_positions,
    motion_sign,
    parse_effect,
    register_effect,
    term,
    unregister_effect,
)


def test_joint_terms_add_their_angle_errors():
    """Harmonic, velocity-sign and torque² terms against their formulas."""
    robot = abb_irb2400_16()
    q = jnp.array([0.3, -0.2, 0.5, 1.1, -0.7, 0.4])
    s = jnp.array([1.0, 0.0, -1.0, 1.0, 0.0, 0.0])
    eff = Effects.from_dict(
        {
            "joint1_harmonic2": [2e-4, -1e-4],
            "joint3_velocity_sign": 5e-5,
            "joint2_torque_squared": 3e-8,
        }
    )
    out = np.asarray(effective_joints(robot, eff, q, jnp.zeros(6), s))
    tau = np.asarray(gravity_torque(robot, q))
    want = np.asarray(q).copy()
    want[0] += 2e-4 * np.sin(2 * 0.3) - 1e-4 * np.cos(2 * 0.3)
    want[2] += 5e-5 * -1.0
    want[1] += 3e-8 * tau[1] * abs(tau[1])
    np.testing.assert_allclose(out, want, atol=1e-15)


def test_led_terms_move_the_observations_along_their_directions():
    """Line-of-sight and emission-axis biases and the per-axis scale against numpy."""
    import jaxlie

    tool = hemispherical_tool()
    pose = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_y_radians(2.6), jnp.array([0.1, -0.2, 2.5])
    )
    poses = jaxlie.SE3(pose.wxyz_xyz[None])
    p, n = jnp.asarray(tool.constellation), jnp.asarray(tool.normals)
    base = np.asarray(led_positions(poses, Effects.zeros(6), p, n))[0]
    eff = Effects.from_dict(
        {
            "led_sight_bias": [3e-5, 1e-4],
            "led_axis_bias": 5e-5,
            "tracker_axis_scale": [1e-4, 0, -2e-4],
        }
    )
    got = np.asarray(led_positions(poses, eff, p, n))[0]
    nc = np.asarray(pose.rotation().as_matrix()) @ np.asarray(n).T
    nc = nc.T
    sight = base / np.linalg.norm(base, axis=1, keepdims=True)
    theta = np.arctan2(np.linalg.norm(np.cross(-sight, nc), axis=1), np.sum(-sight * nc, 1))
    u = (1 - np.cos(theta)) / (1 - np.cos(np.deg2rad(60)))
    moved = base + (3e-5 + 1e-4 * u)[:, None] * sight + (5e-5 * u**2)[:, None] * nc
    want = moved + base * np.array([1e-4, 0.0, -2e-4])
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_motion_sign_is_zero_at_rest():
    t = np.linspace(0, 2, 201)
    q = np.stack([np.where(t < 1, t, 1.0), -np.where(t < 1, 0.0, t - 1)], 1)
    s = motion_sign(t, q, np.array([0.5, 1.5]))
    np.testing.assert_array_equal(s, [[1.0, 0.0], [0.0, -1.0]])


def test_a_registered_term_of_the_velocity_signs_is_marked_for_the_deadband_profile():
    t = register_effect(
        "joint3_stick_slip", lambda q, s, tau: s[2:3], ("value",), joint=3, motion=True
    )
    try:
        assert t.motion and term("joint3_stick_slip").motion and not term("joint3_harmonic1").motion
        assert term("joint3_velocity_sign").motion
        with pytest.raises(UserError, match="only a joint term"):
            register_effect(
                "led_wobble", lambda y, n, th: y[..., None], ("v",), kind="led", motion=True
            )
    finally:
        unregister_effect("joint3_stick_slip")


def test_terms_round_trip_and_bad_values_are_user_errors():
    eff = Effects.from_dict({"joint2_harmonic1": [1e-4, 2e-4], "backlash": 1e-5})
    assert Effects.from_dict(eff.to_dict()).to_dict() == eff.to_dict()
    assert effect_component_names("joint2_harmonic1", (2,)) == [
        "joint2_harmonic1.sin",
        "joint2_harmonic1.cos",
    ]
    name, v = parse_effect("joint4_harmonic3=1e-4,0")
    assert name == "joint4_harmonic3" and v.tolist() == [1e-4, 0.0]
    with pytest.raises(UserError, match="takes 2 values"):
        Effects.zeros(6).with_value("joint2_harmonic1", [1.0, 2.0, 3.0])
    with pytest.raises(UserError, match="unknown effect"):
        Effects.zeros(6).with_value("joint2_harmonic9", 1.0)
    # a robot's dictionary has its own joints' terms only
    assert "joint7_harmonic1" not in dictionary(6) and "joint7_harmonic1" in dictionary(7)
    # the joint angle error maps are terms, but not among the search's defaults
    assert len(default_terms(6)) == len(dictionary(6)) + len(joint_maps(6))
    assert not set(joint_maps(6)) & set(dictionary(6))


def test_a_fitted_term_is_quoted_to_the_digits_its_sigma_supports():
    """σ to two significant digits, the value to the same decimal place: a tight σ keeps
    the value's digits, a wide one drops those it cannot support."""
    harmonic = term("joint1_harmonic2")
    tight = describe(harmonic, np.array([6e-4, 0.0]), np.diag([9.6e-8, 9.6e-8]) ** 2)
    assert tight.startswith("joint 1 angle error 0.600000 ± 0.000096 mrad · sin(2·q1 + "), tight
    wide = describe(harmonic, np.array([2.5e-4, 1e-5]), np.diag([1e-5, 1e-5]) ** 2)
    assert (
        wide == "joint 1 angle error 0.250 ± 0.010 mrad · sin(2·q1 + 0.040 rad) (phase σ 0.040 rad)"
    )
