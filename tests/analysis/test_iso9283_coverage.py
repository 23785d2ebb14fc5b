"""Coverage of the ISO 9283 95 % intervals: over simulated test runs (the attained pose of
each cycle drawn directly as truth + noise), each interval must contain the injected
truth in 95 ± 3 % of the runs.

With 200 runs the binomial standard error of a 95 % rate is √(0.95·0.05/200) = 1.5 %, so
95 ± 3 % is a 2σ window: a correct interval falls outside it for about 5 % of seed sets
per characteristic. The seeds are fixed, so the test is deterministic; the exhaustive
variant runs 1000 runs (SE 0.7 %, window ± 2 %, about 3σ) and shows that the plain
percentile bootstrap under-covers with few cycles where the studentised one does not.
"""

import functools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from robtraj.analysis._iso_path import path_statistics
from robtraj.analysis._quat import quat_multiply
from robtraj.analysis.iso9283 import pose_statistics

SIGMA = 0.1e-3  # [m] per axis, per cycle
ROT_SIGMA = 2e-4  # [rad] per axis, per cycle
OFFSET = np.array([0.3e-3, -0.2e-3, 0.1e-3])  # [m]
ROT_OFFSET = np.array([3e-4, -2e-4, 1e-4])  # [rad]
CP = np.array([1.15, 0.1, 0.9])
CQ = np.array([0.0, 1.0, 0.0, 0.0])
# RP of N(0, σ²I): l = |z| ~ σ·χ₃, E l = 2σ√(2/π), SD l = σ√(3 − 8/π)
RP_PER_SIGMA = 2 * np.sqrt(2 / np.pi) + 3 * np.sqrt(3 - 8 / np.pi)
APPROACH = np.array([[0.15e-3, 0, 0], [0, 0.1e-3, -0.05e-3]])  # [m] per approach direction
STEP = np.array([0.3e-3, -0.1e-3, 0])  # [m] late cycles minus early cycles (drift)
LATE_SCALE = 1.5  # late cycles scatter 1.5× as much


def _quats(rotvec):
    return quat_multiply(Rotation.from_rotvec(rotvec).as_quat()[:, [3, 0, 1, 2]], CQ)


def _run(seed: int, n: int, n_boot: int) -> dict[str, bool]:
    """One simulated test of `n` cycles: does each interval contain the injected truth?"""
    rng = np.random.default_rng(seed)
    x = CP + OFFSET + rng.normal(0.0, SIGMA, (n, 3))
    q = _quats(ROT_OFFSET + rng.normal(0.0, ROT_SIGMA, (n, 3)))
    _, ci = pose_statistics(x, q, CP, CQ, None, None, rng, n_boot)
    truth = {
        "APx": OFFSET[0], "APy": OFFSET[1], "APz": OFFSET[2], "AP": np.linalg.norm(OFFSET),
        "RP": SIGMA * RP_PER_SIGMA, "APa": ROT_OFFSET[0], "APb": ROT_OFFSET[1],
        "APc": ROT_OFFSET[2], "RPa": 3 * ROT_SIGMA, "RPb": 3 * ROT_SIGMA, "RPc": 3 * ROT_SIGMA,
        "AP_angle": np.linalg.norm(ROT_OFFSET), "RP_angle": ROT_SIGMA * RP_PER_SIGMA,
    }  # fmt: skip
    hit = {k: ci[k][0] <= v <= ci[k][1] for k, v in truth.items()}
    # vAP: two approach directions, every other cycle
    g = np.arange(n) % 2
    xg = CP + OFFSET + APPROACH[g] + rng.normal(0.0, SIGMA, (n, 3))
    v, ci = pose_statistics(xg, q, CP, CQ, g, None, rng, n_boot)
    hit["vAP"] = ci["vAP"][0] <= np.linalg.norm(APPROACH[0] - APPROACH[1]) <= ci["vAP"][1]
    # drift: the late third of the cycles shifted by STEP and scattered LATE_SCALE× more
    m = n // 3
    early = CP + OFFSET + rng.normal(0.0, SIGMA, (m, 3))
    late = CP + OFFSET + STEP + rng.normal(0.0, LATE_SCALE * SIGMA, (m, 3))
    qd = _quats(rng.normal(0.0, ROT_SIGMA, (2 * m, 3)))
    _, ci = pose_statistics(np.concatenate([early, late]), qd, CP, CQ, None, m, rng, n_boot)
    hit["dAP"] = (
        ci["dAP"][0] <= np.linalg.norm(OFFSET + STEP) - np.linalg.norm(OFFSET) <= ci["dAP"][1]
    )
    hit["dRP"] = ci["dRP"][0] <= (LATE_SCALE - 1) * SIGMA * RP_PER_SIGMA <= ci["dRP"][1]
    return hit


def _coverage(runs: int, n: int, n_boot: int) -> dict[str, float]:
    hits = [_run(1000 + r, n, n_boot) for r in range(runs)]
    return {k: float(np.mean([h[k] for h in hits])) for k in hits[0]}


def test_pose_intervals_cover_truth_in_95_percent_of_200_runs():
    cov = _coverage(200, 30, 300)
    bad = {k: v for k, v in cov.items() if not 0.92 <= v <= 0.98}
    assert not bad, f"coverage outside 95 ± 3 % over 200 runs: {bad} (all: {cov})"


@pytest.mark.exhaustive
def test_pose_intervals_cover_truth_in_95_percent_of_1000_runs():
    cov = _coverage(1000, 30, 1000)
    bad = {k: v for k, v in cov.items() if not 0.93 <= v <= 0.97}
    assert not bad, f"coverage outside 95 ± 2 % over 1000 runs: {bad} (all: {cov})"


@pytest.mark.exhaustive
@pytest.mark.parametrize("n", [5, 10])
def test_percentile_bootstrap_under_covers_where_t_does_not(n):
    """With few cycles the percentile bootstrap of a mean (AP per axis) under-covers:
    its spread is the plug-in σ/√n (1/n, not 1/(n − 1)) and it ignores t's tails."""
    runs, truth = 2000, OFFSET[0]
    hit_t, hit_pct = [], []
    for r in range(runs):
        rng = np.random.default_rng(r)
        x = CP + OFFSET + rng.normal(0.0, SIGMA, (n, 3))
        _, ci = pose_statistics(x, _quats(rng.normal(0.0, ROT_SIGMA, (n, 3))), CP, CQ,
                                None, None, rng, 200)  # fmt: skip
        hit_t.append(ci["APx"][0] <= truth <= ci["APx"][1])
        boot = (x - CP)[rng.integers(0, n, (2000, n)), 0].mean(axis=1)
        lo, hi = np.quantile(boot, [0.025, 0.975])
        hit_pct.append(lo <= truth <= hi)
    se = np.sqrt(0.95 * 0.05 / runs)  # 0.5 %
    assert abs(np.mean(hit_t) - 0.95) < 3 * se
    assert np.mean(hit_pct) < 0.95 - 3 * se, np.mean(hit_pct)


def _path_run(seed: int, passes: int, n_boot: int) -> dict[str, bool]:
    """A path of 20 normal planes: each pass crosses them along the command + a bow
    b·sin(πf) across the path + N(0, σ²) per plane; its speed is vc·(1 + N(0, 0.02²))."""
    rng = np.random.default_rng(seed)
    f = (np.arange(20) + 0.5) / 20
    c = CP + f[:, None] * np.array([0.0, 0.3, 0.0])
    bow = 0.5e-3 * np.sin(np.pi * f)[:, None] * np.array([1.0, 0.0, 0.0])
    x = c + bow + rng.normal(0.0, SIGMA, (passes, 20, 3))
    qc = np.broadcast_to(CQ, (20, 4))
    q = _quats(rng.normal(0.0, ROT_SIGMA, (passes * 20, 3))).reshape(passes, 20, 4)
    vc = 0.2
    v = vc * (1 + 0.02 * rng.normal(size=passes))
    _, ci = path_statistics(x, q, c, qc, v, vc, rng, n_boot)
    truth = {"AT": 0.5e-3, "RT": SIGMA * RP_PER_SIGMA, "AV": 0.0, "RV": 0.06}
    return {k: ci[k][0] <= val <= ci[k][1] for k, val in truth.items()}


@functools.cache
def _path_coverage() -> dict[str, float]:
    hits = [_path_run(5000 + r, 10, 300) for r in range(1000)]
    return {k: float(np.mean([h[k] for h in hits])) for k in hits[0]}


@pytest.mark.exhaustive
def test_path_interval_coverage():
    """1000 runs (SE 0.7 %, ± 2 % ≈ 3σ). AV, RV: 95 ± 2 %. RT is a maximum over planes
    of equal-valued truths here; its simultaneous-interval bound is conservative by
    construction (at least 95 %; measured 97.6 %)."""
    cov = _path_coverage()
    assert all(0.93 <= cov[k] <= 0.97 for k in ("AV", "RV")), cov
    assert cov["RT"] >= 0.93, cov


@pytest.mark.exhaustive
@pytest.mark.xfail(strict=True, reason="AT's bootstrap-t interval covers 90.4 % (1000 runs)")
def test_path_accuracy_interval_coverage():
    """AT = maximum over planes of |barycentre − command|: the studentised bootstrap
    under-covers (the maximum of estimates is biased up near a flat top)."""
    cov = _path_coverage()
    assert 0.93 <= cov["AT"] <= 0.97, cov
