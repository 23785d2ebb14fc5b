"""The recording's noise model against the simulator's camera model (angle- and
distance-dependent noise), and its immunity to systematic effects."""

import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from robtraj._errors import UserError
from robtraj.estimate import estimate_noise, observation_angles
from robtraj.model import CameraModel, noise_sigma
from robtraj.sim import simulate


def _recording(effects=None, seed=2):
    return simulate("calibration", seed=seed, duration=24.0, rate=100.0, effects=effects)


def _true_variance(rec):
    """Per-axis variance [m²] of every observation from the camera model at the true pose."""
    pose = rec.truth.tool_pose
    rot = np.asarray(jaxlie.SO3(jnp.asarray(pose.quaternion_wxyz)).as_matrix())
    leds = np.einsum("fij,mj->fmi", rot, rec.truth.constellation) + pose.position[:, None]
    nrm = np.einsum("fij,mj->fmi", rot, rec.tool.normals)
    to_cam = -leds / np.linalg.norm(leds, axis=-1, keepdims=True)
    theta = np.arctan2(np.linalg.norm(np.cross(to_cam, nrm), axis=-1), np.sum(to_cam * nrm, -1))
    dist = np.linalg.norm(leds, axis=-1)
    sig = np.asarray(noise_sigma(CameraModel(), jnp.asarray(theta), jnp.asarray(dist)))
    return sig**2, theta, dist


@pytest.fixture(scope="module")
def plain():
    rec = _recording()
    angles = observation_angles(rec)
    return rec, angles, estimate_noise(rec.positions, angles, rec.led_ids)


def test_variance_matches_the_camera_model_by_angle_and_distance(plain):
    rec, angles, model = plain
    truth, theta, dist = _true_variance(rec)
    est = model.observation_variance(rec.positions, angles)
    seen = rec.visible
    ratio = est[seen].mean() / truth[seen].mean()
    # the jackknife standard error is itself uncertain (8 blocks): allow 4 of them
    assert 0.002 < model.level_rel_se < 0.05, model.level_rel_se
    assert abs(ratio - 1) < 4 * model.level_rel_se, (ratio, model.level_rel_se)
    # angle and distance dependence: every tercile holds a third of the data, so its
    # standard error is about √3 times the whole's
    for x, grows in ((theta[seen], 3.0), (dist[seen], 1.2)):
        cuts = np.quantile(x, [1 / 3, 2 / 3])
        parts = (x < cuts[0], (x >= cuts[0]) & (x < cuts[1]), x >= cuts[1])
        for part in parts:
            r = est[seen][part].mean() / truth[seen][part].mean()
            assert abs(r - 1) < 4 * np.sqrt(3) * model.level_rel_se, r
        # the dependence is there to be found: outer against inner tercile of the truth
        assert truth[seen][parts[2]].mean() > grows * truth[seen][parts[0]].mean()


def test_a_systematic_led_bias_does_not_enter_the_noise(plain):
    """A 200 µm emission-angle bias moves the LEDs by up to 0.2 mm but barely changes a
    distance from one frame to the next: the noise model is that of the same noise
    without it (same seed, same noise draws) to well within its standard error, while
    the residual of a per-frame rigid fit grows."""
    rec, angles, model = plain
    biased = _recording({"led_angle_bias": 200e-6})
    other = estimate_noise(biased.positions, angles, biased.led_ids)
    both = rec.visible & biased.visible
    a = model.observation_variance(rec.positions, angles)[both].mean()
    b = other.observation_variance(biased.positions, angles)[both].mean()
    assert abs(b / a - 1) < 0.25 * model.level_rel_se, (b / a, model.level_rel_se)


def test_without_normals_the_model_depends_on_distance_and_led_only(plain):
    rec, _, _ = plain
    model = estimate_noise(rec.positions, None, rec.led_ids)
    assert model.angle_knots.size == 1
    truth, _, _ = _true_variance(rec)
    var = model.observation_variance(rec.positions, np.full(rec.positions.shape[:2], np.nan))
    ratio = var[rec.visible].mean() / truth[rec.visible].mean()
    assert abs(ratio - 1) < 4 * model.level_rel_se + 0.05, ratio


def test_too_few_consecutive_frames_is_a_clear_error():
    pos = np.full((30, 4, 3), np.nan)
    pos[::2, :2] = 1.0  # never three consecutive frames
    with pytest.raises(UserError, match="noise of the recording cannot be estimated"):
        estimate_noise(pos, None, np.arange(4))


def _apply(poses: jaxlie.SE3, body: np.ndarray) -> np.ndarray:
    """`body` `(K, 3)` mapped by each of `poses` `(N,)`: `(N, K, 3)`."""
    return (
        np.asarray(poses.as_matrix()[:, None, :3, :3] @ body[None, :, :, None])[..., 0]
        + np.asarray(poses.translation())[:, None, :]
    )


def test_points_without_noise_of_their_own_are_a_clear_error():
    """Points computed from 6-DOF poses (`robtraj import --format pose-csv`) keep their
    distances to rounding: no noise model, rather than variances of 1e-33 m² that would
    weight the calibration by 10³³."""
    rng = np.random.default_rng(0)
    body = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]])
    poses = jaxlie.SE3.exp(jnp.asarray(rng.normal(0.0, 0.3, (500, 6)) + [0, 0, 2, 0, 0, 0]))
    pos = _apply(poses, body)
    with pytest.raises(UserError, match="no LED noise of their own"):
        estimate_noise(pos, None, np.arange(1, 5))
    # with 1 µm of noise the same points give a model of 1 µm
    model = estimate_noise(pos + rng.normal(0.0, 1e-6, pos.shape), None, np.arange(1, 5))
    sigma = np.sqrt(np.mean(model.variance))
    assert abs(sigma / 1e-6 - 1) < 4 * model.level_rel_se + 0.05, sigma


def test_a_knot_only_one_time_block_reaches_leaves_the_level_error_finite():
    """The jackknife of the model's level over time blocks: in the `workspace` scenario
    (seed 26) three variance knots are reached by one block only; without it they are not
    determined and stay at the full fit's value, so the relative standard error is that
    of the other seeds (2–7 % for seeds 20–39), not 1e145."""
    rec = simulate("workspace", seed=26, duration=24.0, rate=25.0)
    model = estimate_noise(rec.positions, observation_angles(rec), rec.led_ids)
    assert 0.005 < model.level_rel_se < 0.2, model.level_rel_se


def test_an_undetermined_knot_is_held_and_the_others_solved_as_nnls():
    """`_held_out` against scipy's NNLS on the least-squares problem whose normal
    equations it is given, with the undetermined column's contribution moved to the
    right-hand side."""
    from scipy.optimize import nnls

    from robtraj.estimate._noise import _held_out

    rng = np.random.default_rng(0)
    a = rng.uniform(0.0, 1.0, size=(40, 5))
    a[:, 2] = 0.0  # the left-out block held all of knot 2's observations
    truth = np.array([1.0, 0.5, 0.0, 2.0, 0.2])
    y = a @ truth + 0.01 * rng.normal(size=40)
    full = np.array([0.9, 0.4, 3.0, 2.1, 0.3])  # the full fit's values
    got = _held_out(a.T @ a, a.T @ y, np.full(5, 10.0), full)
    free = np.array([True, True, False, True, True])
    want, _ = nnls(a[:, free], y - a[:, ~free] @ full[~free])
    assert got[2] == full[2]
    np.testing.assert_allclose(got[free], want, rtol=1e-6, atol=1e-9)
