"""The poses a calibration suggests measuring next: their information is the engine's
own normal matrix, and they determine what the run left undetermined."""

import jax.numpy as jnp
import numpy as np
import pytest

from robtraj.estimate import calibration as C
from robtraj.estimate._calib_setup import setup
from robtraj.estimate._next_poses import _information, candidate_joints
from robtraj.model import interpolate_joints
from robtraj.sim import simulate


@pytest.fixture(scope="module")
def constant_orientation():
    rec = simulate("crossing", seed=3, duration=10.0, rate=25.0)
    return rec, C.fit(rec, suggest=6)


def test_information_of_the_recordings_own_frames_is_its_normal_matrix(constant_orientation):
    """Summed over the recording's frames (each taken as a static pose at its joint
    angles, with its own weights), the per-pose information equals the normal matrix the
    engine accumulates over the chunks — to rounding (the crossing run has no effect
    that depends on the motion)."""
    rec, res = constant_orientation
    st = setup(rec, res.estimated, res, res.weights, None, lambda _m: None)
    data = st.data
    q = interpolate_joints(
        jnp.asarray(data.log_time), jnp.asarray(data.joints), jnp.asarray(data.time)
    )
    frames = st.bundle.chunks
    sw = np.concatenate(
        [
            frames.block(i).frames["sqrt_weight"].reshape(-1, data.n_leds)
            for i in range(frames.n_blocks)
        ]
    )[: data.n_frames]
    total = np.asarray(_information(st.bundle, q, jnp.asarray(sw))).sum(0)
    d = np.sqrt(np.diag(st.h0))
    ok = d > 0
    scaled = (total - st.h0)[np.ix_(ok, ok)] / np.outer(d[ok], d[ok])
    assert np.max(np.abs(scaled)) < 1e-10


def test_suggested_poses_determine_the_undetermined_translations(constant_orientation):
    """One pose turned about one more axis leaves a null direction (the translation along
    the turn's axis); the second determines all three, as the D-optimal choice predicts."""
    _, res = constant_orientation
    ident = res.identifiability
    names = [f"{t}.t{c}" for t in ("camera_from_base", "flange_from_tool") for c in "xyz"]
    assert sorted(ident["undetermined"]) == sorted(names)
    nxt = ident["next_poses"]
    assert len(nxt["joints_rad"]) == 6 and min(nxt["leds_seen"]) >= 4
    assert all(nxt["sigma_before"][n] is None for n in names)
    assert any(nxt["sigma_after"][0][n] is None for n in names)
    after = [nxt["sigma_after"][1][n] for n in names]
    assert all(s is not None and 0 < s < 20e-6 for s in after), after
    # each further pose can only add information
    for a, b in zip(nxt["sigma_after"][1:], nxt["sigma_after"][2:]):
        assert all(b[n] <= a[n] * (1 + 1e-9) for n in names)


def test_candidates_turn_the_wrist_of_logged_configurations():
    q = np.array([[0.1, 0.2, 0.3, 0.4, 0.5, 0.6], [0.2, 0.2, 0.3, 0.4, 0.5, 0.6]])
    c = candidate_joints(q, n_base=2)
    assert np.allclose(c[:, :3], np.repeat(q[:, :3], c.shape[0] // 2, 0))
    moved = np.abs(c[:, 3:] - np.repeat(q[:, 3:], c.shape[0] // 2, 0))
    assert set(np.round(np.degrees(moved[moved > 0]), 6)) == {20.0, 40.0}
    assert (moved > 0).sum(1).max() == 2  # one or two wrist joints at a time
