"""Static segments, registration, weighting schemes and the pose pipeline on simulated data."""

import jax.numpy as jnp
import numpy as np
import pytest

from robtraj import UserError
from robtraj.estimate import (
    LedFeatures,
    chunked_led_variance,
    estimate_poses,
    register_weighting,
    static_segments,
    weighting_schemes,
)
from robtraj.estimate._poses import _quat_matrix, errors_against
from robtraj.model import CameraModel, noise_sigma
from robtraj.sim import simulate


@pytest.fixture(scope="module")
def paper():
    return simulate("paper", seed=11, duration=30.0, rate=250.0)


def test_static_segments_match_the_program_dwells(paper):
    rec = paper
    segs = static_segments(rec.time, rec.positions)
    # truth: the tool stands still when the true pose does not change
    p = rec.truth.tool_pose.position
    speed = np.linalg.norm(np.gradient(p, rec.time, axis=0), axis=1)
    for a, b in segs:
        assert np.max(speed[a:b]) < 2e-3, (a, b)
    # the 1.3 s start dwell is found
    assert segs[0][0] == 0 and rec.time[segs[0][1] - 1] > 0.9


def _gauge_truth(rec):
    """Truth constellation expressed in the registration's gauge: the tool frame in which
    the nominal reference LEDs best fit the true reference LEDs."""
    from scipy.spatial.transform import Rotation

    idx = np.searchsorted(rec.led_ids, rec.tool.reference_leds)
    nom, tru = rec.tool.constellation[idx], rec.truth.constellation[idx]
    # true reference triangle moved onto the nominal one (least squares, no scale)
    a, b = tru - tru.mean(0), nom - nom.mean(0)
    r, _ = Rotation.align_vectors(b, a)
    return r.apply(rec.truth.constellation - tru.mean(0)) + nom.mean(0)


def test_registration_recovers_constellation_within_uncertainty():
    rec = simulate("calibration", seed=4, duration=40.0, rate=250.0)
    est = estimate_poses(rec, weighting="inverse_variance")
    reg = est.registration
    assert reg is not None and est.constellation_source == "registered"
    truth = _gauge_truth(rec)
    ok = reg.referenced
    assert ok.sum() >= 14
    err = np.linalg.norm(reg.positions[ok] - truth[ok], axis=1)
    # registration recovers the 50 µm perturbations far better than nominal does
    nominal_err = np.linalg.norm(rec.tool.constellation[ok] - truth[ok], axis=1)
    assert np.median(err) < 0.3 * np.median(nominal_err)
    # normalised errors (3-D distance over per-axis σ: χ with 3 dof, mean ≈ 1.6)
    z = err / (np.sqrt(3) * reg.uncertainty[ok])
    assert np.mean(z) < 3.0, z


def test_unreferenced_leds_get_reasons(paper):
    rec = paper
    positions = rec.positions.copy()
    positions[:, 5] = np.nan  # LED 6 never seen
    est = estimate_poses(rec.replace(positions=positions), weighting="uniform")
    assert est.registration.reasons[int(rec.led_ids[5])] == "never seen"


def _crb_position_sigma(rec):
    """Cramér–Rao bound of the tool position per frame from the camera noise model:
    Fisher information of the 6-DOF pose from LEDs with isotropic σ_k (known
    constellation), position block of its inverse."""
    cam = CameraModel()
    q, t = rec.truth.tool_pose.quaternion_wxyz, rec.truth.tool_pose.position
    r = _quat_matrix(q)
    p = rec.truth.constellation
    leds = np.einsum("fij,mj->fmi", r, p) + t[:, None]
    nrm = np.einsum("fij,mj->fmi", r, rec.tool.normals)
    to_cam = -leds / np.linalg.norm(leds, axis=-1, keepdims=True)
    theta = np.arctan2(np.linalg.norm(np.cross(to_cam, nrm), axis=-1), np.sum(to_cam * nrm, -1))
    sig = np.asarray(
        noise_sigma(cam, jnp.asarray(theta), jnp.asarray(np.linalg.norm(leds, axis=-1)))
    )
    seen = rec.visible
    w = np.where(seen, 1 / sig**2, 0.0)
    # J_k = [I, -[R p_k]x]: y_k = t + exp(ω)R p_k
    rp = leds - t[:, None]
    info = np.zeros((len(t), 6, 6))
    for k in range(p.shape[0]):
        x = rp[:, k]
        skew = np.zeros((len(t), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -x[:, 2], x[:, 1], -x[:, 0]
        skew -= np.transpose(skew, (0, 2, 1))
        j = np.concatenate([np.broadcast_to(np.eye(3), skew.shape), -skew], axis=2)
        info += w[:, k, None, None] * np.einsum("fai,faj->fij", j, j)
    cov = np.linalg.inv(info)
    return np.sqrt(np.trace(cov[:, :3, :3], axis1=1, axis2=2))


def test_quality_weighting_near_cramer_rao_and_beats_uniform(paper):
    """Pose error with the true constellation (isolates the weighting) against the CRB.

    `led_noise` (per-LED noise from pair variances) reaches the bound within 20 %;
    `emission_angle` (1/σ² of the noise model estimated from the recording: emission
    angle, distance, LED) within 10 % (measured 0.5 % above it on another seed);
    the paper's `inverse_variance` does not (its summed distance mixes in the partners'
    noise and jumps when partners appear or vanish) but it, too, beats uniform weighting
    near the visibility edge, the paper's Figure 4 effect.
    """
    rec = paper
    crb = _crb_position_sigma(rec)
    res = {}
    schemes = ["uniform", "inverse_variance", "pairwise_inverse_variance", "led_noise"]
    for scheme in [*schemes, "emission_angle"]:
        est = estimate_poses(rec, weighting=scheme, constellation=rec.truth.constellation)
        pe, _ = errors_against(
            est, rec.truth.tool_pose.position, rec.truth.tool_pose.quaternion_wxyz, gauge=False
        )
        res[scheme] = pe
    ok = np.all([np.isfinite(v) for v in res.values()], axis=0)
    rms = {k: np.sqrt(np.mean(v[ok] ** 2)) for k, v in res.items()}
    bound = np.sqrt(np.mean(crb[ok] ** 2))
    assert 0.9 * bound < rms["led_noise"] < 1.2 * bound, (rms, bound)
    assert 0.9 * bound < rms["emission_angle"] < 1.1 * bound, (rms, bound)
    assert rms["pairwise_inverse_variance"] < rms["uniform"]
    # near the visibility edge (frames with a low-signal LED) quality weighting wins
    edge = ok & (rec.status == 3).any(1)
    e = {k: np.sqrt(np.mean(v[edge] ** 2)) for k, v in res.items()}
    assert e["led_noise"] < 0.85 * e["uniform"], e
    assert e["emission_angle"] < 0.85 * e["uniform"], e


def test_paper_inverse_variance_beats_uniform_without_dropouts():
    """The paper's LED variance helps when LEDs do not drop out for single frames; a
    drop-out makes every partner's summed distance jump, which the windowed variance
    then reads as noise (with the default 0.2 % drop-outs it loses to uniform)."""
    rec = simulate("paper", seed=11, duration=30.0, rate=250.0, camera=CameraModel(dropout=0.0))
    edge = (rec.status == 3).any(1)
    e = {}
    for scheme in ["uniform", "inverse_variance"]:
        est = estimate_poses(rec, weighting=scheme, constellation=rec.truth.constellation)
        pe, _ = errors_against(
            est, rec.truth.tool_pose.position, rec.truth.tool_pose.quaternion_wxyz, gauge=False
        )
        e[scheme] = np.sqrt(np.nanmean(pe[edge] ** 2))
    assert e["inverse_variance"] < 0.95 * e["uniform"], e


def test_every_builtin_scheme_runs_and_a_user_scheme_registers(paper):
    rec = simulate("paper", seed=2, duration=4.0, rate=250.0)
    for name in [
        "uniform",
        "inverse_variance",
        "pairwise_inverse_variance",
        "threshold",
        "robust",
        "emission_angle",
    ]:
        assert name in weighting_schemes()
        est = estimate_poses(rec, weighting=name, register=False)
        assert est.valid.mean() > 0.99
        assert np.nanmedian(est.rms) < 100e-6

    @register_weighting("apex_only_heavy", needs=())
    def heavy(f: LedFeatures, factor: float = 10.0):
        return jnp.where(f.visible, 1.0, 0.0).at[:, 0].multiply(factor)

    est = estimate_poses(rec, weighting="apex_only_heavy", register=False, params={"factor": 5.0})
    assert est.valid.all()


def test_too_few_leds_is_a_clear_error_or_flag(paper):
    rec = paper
    positions = rec.positions.copy()
    positions[:, 2:] = np.nan
    with pytest.raises(UserError, match="three or more LEDs"):
        estimate_poses(rec.replace(positions=positions))
    positions = rec.positions.copy()
    positions[:100, 3:] = np.nan  # only 3 LEDs ever: first frames may have < 3 seen
    est = estimate_poses(rec.replace(positions=positions), register=False)
    few = rec.replace(positions=positions).visible.sum(1) < 3
    assert not est.valid[few].any() and np.isnan(est.position[few]).all()


def test_chunked_variance_equals_one_call(paper):
    from robtraj.jax_ops import led_variance

    pos = paper.positions[:3000]
    whole = np.asarray(led_variance(jnp.asarray(pos), 25, variant="paper"))
    chunked = chunked_led_variance(pos, 25, "paper", chunk=700)
    np.testing.assert_allclose(chunked, whole, rtol=1e-10, equal_nan=True)
