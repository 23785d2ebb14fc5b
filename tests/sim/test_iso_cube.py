"""The simulated ISO 9283 cube test end to end: LED recording → poses → ISO 9283, against
the truths `iso_cube` injects (`iso_cube_truth`)."""

import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from robtraj.analysis import iso9283
from robtraj.estimate import estimate_poses
from robtraj.sim import iso_cube_cycles, iso_cube_truth, simulate

DURATION, RATE = 81.0, 100.0  # 4 pose cycles: both approach directions twice
# [m] limit band for the stabilisation time: between the ringing's first (0.99 mm) and
# second (0.19 mm) peaks, each ≥ 30 per-axis noise σ (~8 µm per frame) away from it
BAND = 0.43e-3


def _se3(p):
    return jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3(jnp.asarray(p.quaternion_wxyz)), jnp.asarray(p.position)
    )


@pytest.fixture(scope="module")
def cube():
    return _measure()


def _measure():
    rec = simulate("iso_cube", seed=3, duration=DURATION, rate=RATE)
    est = estimate_poses(rec, constellation=rec.truth.constellation)
    # measured tool in the camera → controller TCP in the base frame, through the true
    # camera placement and tool mount: only the tracker's noise is left
    cam_tool = jaxlie.SE3(
        jnp.concatenate([jnp.asarray(est.quaternion_wxyz), jnp.asarray(est.position)], -1)
    )
    fix = _se3(rec.truth.flange_from_tool).inverse() @ _se3(rec.tool.flange_from_tool)
    tcp = _se3(rec.truth.camera_from_base).inverse() @ cam_tool @ fix
    pos, quat = np.array(tcp.translation()), np.array(tcp.rotation().wxyz)
    pos[~est.valid] = np.nan
    quat[~est.valid] = np.nan
    res = iso9283(rec.program, rec.time, pos, quat, segment=rec.program.segment, band=BAND)
    return rec, pos, res


def test_characteristics_match_injected_truth(cube):
    rec, pos, res = cube
    truth = iso_cube_truth(DURATION, BAND)
    n = iso_cube_cycles(DURATION)
    # per-frame tracker noise from the still frames (second halves of the dwells); a
    # dwell's attained pose averages ~RATE/2 frames, so its scatter is σ/√(RATE/2)
    # (robust: median absolute frame-to-frame step where the TCP stands, /√2)
    step = np.diff(pos, axis=0)
    still = np.linalg.norm(step, axis=1) * RATE < 5e-3
    sigma = np.max(np.median(np.abs(step[still]), axis=0) / 0.6745 / np.sqrt(2))
    se_dwell = sigma / np.sqrt(RATE / 2)
    # P1 is also the start and end of the program; the path test's start is a sixth pose
    assert len(res.poses) == 6
    for p in res.poses[1:5]:
        t = truth[p.name]
        np.testing.assert_allclose(p.commanded_position, t["commanded"], atol=1e-12)
        assert p.n_cycles == n
        # barycentres of n/2 attainments per direction: 4σ of their difference
        assert abs(p.vAP - t["vAP"]) < 4 * se_dwell * np.sqrt(4 / n), (p.name, p.vAP, t["vAP"])
        # dAP: early and late barycentres of n//3 ≥ 2 cycles each
        m = max(2, n // 3)
        assert abs(p.dAP - t["dAP"]) < 4 * se_dwell * np.sqrt(2 / m), (p.name, p.dAP, t["dAP"])
        # overshoot within 10 %: a frame's noise (4σ ≈ 3 % of the 1 mm overshoot) fits
        assert 4 * sigma < 0.1 * t["overshoot"]
        assert abs(p.overshoot_mean - t["overshoot"]) < 0.1 * t["overshoot"], p.overshoot_mean
        # stabilisation time to one frame (1/RATE: 12 % of it at 100 Hz; the 10 % check
        # at a finer rate is in tests/analysis/test_iso9283.py)
        assert abs(p.t_stab_mean - t["t_stab"]) <= 1 / RATE + 1e-9, (p.t_stab_mean, t["t_stab"])
        lo, hi = p.ci["vAP"]
        assert lo <= p.vAP <= hi
