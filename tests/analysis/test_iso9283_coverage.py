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

from robtraj.analysis._iso_ci import (
    N_BOOT,
    _mean_length,
    abs_interval,
    max_length_interval,
    max_scale_interval,
    rp_difference,
    rp_gaussian,
    t_interval,
    three_s_interval,
)
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


ROT_BOW = np.array([4e-4, -3e-4, 2e-4])  # [rad] rotation vector of the bow's orientation error


def _path_run(seed: int, passes: int, n_boot: int) -> dict[str, bool]:
    """A path of 20 normal planes: each pass crosses them along the command + a bow
    b·sin(πf) across the path + N(0, σ²) per plane, with the orientation error
    exp(ROT_BOW·sin(πf) + N(0, ROT_SIGMA²)); its speed is vc·(1 + N(0, 0.02²)). The
    truths are the maxima over the planes (for AT two planes tie at the top: f = 0.475,
    0.525; for RT all 20 tie)."""
    rng = np.random.default_rng(seed)
    f = (np.arange(20) + 0.5) / 20
    c = CP + f[:, None] * np.array([0.0, 0.3, 0.0])
    bow = 0.5e-3 * np.sin(np.pi * f)[:, None] * np.array([1.0, 0.0, 0.0])
    x = c + bow + rng.normal(0.0, SIGMA, (passes, 20, 3))
    qc = np.broadcast_to(CQ, (20, 4))
    rot = np.sin(np.pi * f)[:, None] * ROT_BOW + rng.normal(0.0, ROT_SIGMA, (passes, 20, 3))
    q = _quats(rot.reshape(-1, 3)).reshape(passes, 20, 4)
    vc = 0.2
    v = vc * (1 + 0.02 * rng.normal(size=passes))
    _, ci = path_statistics(x, q, c, qc, v, vc, rng, n_boot)
    top = np.max(np.sin(np.pi * f))
    # a, b, c are the base-frame rotation vector's components to second order (~1e-7 rad,
    # 0.2 % of a plane mean's standard error), the single angle its length
    truth = {
        "AT": 0.5e-3 * top, "ATa": abs(ROT_BOW[0]) * top, "ATb": abs(ROT_BOW[1]) * top,
        "ATc": abs(ROT_BOW[2]) * top, "AT_angle": np.linalg.norm(ROT_BOW) * top,
        "RT": SIGMA * RP_PER_SIGMA, "RTa": 3 * ROT_SIGMA, "RTb": 3 * ROT_SIGMA,
        "RTc": 3 * ROT_SIGMA, "AV": 0.0, "RV": 0.06,
    }  # fmt: skip
    return {k: ci[k][0] <= val <= ci[k][1] for k, val in truth.items()}


@functools.cache
def _path_coverage(runs: int, n_boot: int) -> dict[str, float]:
    hits = [_path_run(5000 + r, 10, n_boot) for r in range(runs)]
    return {k: float(np.mean([h[k] for h in hits])) for k in hits[0]}


_AT = ("AT", "ATa", "ATb", "ATc", "AT_angle")
#: profiles of the mean error's length over the 20 planes (× 0.5 mm): the bow's two top
#: planes tie; f⁸ has one top plane, the next 0.14 mm (3.1 standard errors of a plane's
#: mean at 5 passes) below; f⁴ has the next one 0.086 mm (1.9 at 5 passes) below
_PROFILES = {"bow": lambda f: np.sin(np.pi * f), "f8": lambda f: f**8, "f4": lambda f: f**4}


def _at_coverage(profile: str, runs: int, passes: int, n_boot: int) -> float:
    """Coverage of `max_length_interval` (AT) over `runs` draws of `passes` passes."""
    f = (np.arange(20) + 0.5) / 20
    mean = 0.5e-3 * _PROFILES[profile](f)[:, None] * np.array([1.0, 0.0, 0.0])
    truth = np.max(np.linalg.norm(mean, axis=-1))
    hits = []
    for r in range(runs):
        rng = np.random.default_rng(7000 + r)
        lo, hi = max_length_interval(mean + rng.normal(0.0, SIGMA, (passes, 20, 3)), rng, n_boot)
        hits.append(lo <= truth <= hi)
    return float(np.mean(hits))


def test_path_accuracy_interval_with_one_plane_is_students_t():
    """One plane on top (the others 20 standard errors below, one with two passes
    missing): the studentised restricted bootstrap reduces to Student's t on that plane,
    up to Monte-Carlo error (20 000 draws: the 97.5 % quantile of t₉ to ±0.027, so ends
    within 0.11 standard errors, 4σ)."""
    rng = np.random.default_rng(4)
    for _ in range(3):
        e = np.array([1.0, 0.0, 0.0])[None, :, None] + rng.normal(0.0, 0.15, (10, 3, 1))
        e[[2, 5], 1] = np.nan
        lo, hi = max_length_interval(e, rng, 20_000)
        ref = t_interval(e[:, 0, 0])
        se = np.std(e[:, 0, 0], ddof=1) / np.sqrt(10)
        np.testing.assert_allclose([lo, hi], ref, atol=0.11 * se)


def test_path_accuracy_interval_covers_with_one_top_plane_and_at_a_tie():
    """AT = max over planes of |barycentre − command|, 300 runs of 10 passes (SE 1.3 %;
    95 ± 3 % is 2.4σ, a correct interval falls outside for ~2 % of seed sets), 1000
    bootstrap draws: one plane on top (f⁸) and two tied at the top (bow) both within
    95 ± 3 % (measured 94.0, 97.0 %). The t/z-scaled bootstrap of the raw maximum this
    replaced covered 98.3 % for ATb/ATc where more planes tie, a bootstrap-t of the
    maximum centred on the estimate 90.4 % on the tie (1000 runs each)."""
    cov = {p: _at_coverage(p, 300, 10, 1000) for p in ("f8", "bow")}
    assert all(0.92 <= c <= 0.98 for c in cov.values()), cov


#: σ profiles over the 20 planes for RT: all tie; one plane 3× the rest (f⁸ reaches 3 only
#: at the last plane, the next at 2.07); the last two planes tie at 3× the rest
_RT_PROFILES = {
    "tie": lambda f: np.ones_like(f),
    "one": lambda f: 1.0 + 2.0 * f**8,
    "two": lambda f: 1.0 + 2.0 * (f > 0.9),
}


def _rt_coverage(profile: str, passes: int, runs: int, n_boot: int = 400) -> float:
    """Coverage of `max_scale_interval` with RT per plane drawn from its sampling
    distribution, RT_k·√(χ²_ν/ν) with ν = 3(passes − 1) (isotropic scatter)."""
    f = (np.arange(20) + 0.5) / 20
    rt = _RT_PROFILES[profile](f)
    nu = np.full(20, 3.0 * (passes - 1))
    hits = []
    for r in range(runs):
        rng = np.random.default_rng(9000 + r)
        lo, hi = max_scale_interval(rt * np.sqrt(rng.chisquare(nu) / nu), nu, rng, n_boot)
        hits.append(lo <= rt.max() <= hi)
    return float(np.mean(hits))


def test_rt_interval_with_one_plane_is_the_chi2_interval():
    """One plane: the restricted bootstrap reduces to T/q(w), w ~ √(χ²_ν/ν), i.e. the
    closed-form χ² interval of a 3·S term, up to Monte-Carlo error (20 000 draws: the
    2.5 % quantile of w to ~0.3 %)."""
    rng = np.random.default_rng(3)
    x = rng.normal(0.0, 1.0, 10)
    lo, hi = max_scale_interval(np.array([3.0 * np.std(x, ddof=1)]), np.array([9.0]), rng, 20_000)
    ref = three_s_interval(x)
    np.testing.assert_allclose([lo, hi], ref, rtol=0.02)


def test_rt_interval_covers_from_a_tie_to_one_top_plane():
    """RT = max over planes of each plane's RP. 1000 runs per profile (SE 0.7 %; 95 ± 3 %
    is 4σ) at 10 passes: all planes tied (measured 95.6 %), one on top (94.4 %), two
    tied on top (96.6 %). The simultaneous (Bonferroni) per-plane intervals this
    replaced covered 97.6 % at the tie and 100 % where one plane's σ is 1.1× the next."""
    cov = {p: _rt_coverage(p, 10, 1000) for p in _RT_PROFILES}
    assert all(0.92 <= c <= 0.98 for c in cov.values()), cov


@pytest.mark.exhaustive
@pytest.mark.parametrize("passes", [5, 30])
def test_rt_interval_coverage_with_few_and_many_passes(passes):
    """As above at 5 and 30 passes (measured 93.9–96.2 %)."""
    cov = {p: _rt_coverage(p, passes, 1000) for p in _RT_PROFILES}
    assert all(0.92 <= c <= 0.98 for c in cov.values()), cov


@pytest.mark.exhaustive
def test_path_interval_coverage():
    """1000 runs (SE 0.7 %, ± 2 % ≈ 3σ) through `path_statistics` with the default
    bootstrap size: AV, RV and RT (position, a/b/c; all planes tied) within 95 ± 2 %
    (measured: AV 93.5, RV 94.8, RT 96.1, RTa/b/c 94.6/95.1/95.6 %; RT 94.0 % since RP's
    ν is the delta method's, `rp_scale`, measured with the AT intervals left out, i.e.
    other bootstrap draws, where the plug-in ν gave 96.2 %)."""
    cov = _path_coverage(1000, N_BOOT)
    keys = ("AV", "RV", "RT", "RTa", "RTb", "RTc")
    assert all(0.93 <= cov[k] <= 0.97 for k in keys), cov


@pytest.mark.exhaustive
def test_path_accuracy_interval_coverage():
    """AT (position, a/b/c, single angle) on the bow through `path_statistics`, 10 passes,
    1000 runs, default bootstrap size: within 95 ± 3 % (SE 0.7 %, 4σ). Two planes tie at
    the top, and for a/b/c (3–6 standard errors from 0) 4–6 planes lie within 0.3
    standard errors of it, where no valid upper end can miss the truth, so coverage sits
    up to 2.5 % above 95 % (measured: AT 96.5, ATa 95.0, ATb 97.6, ATc 96.9, AT_angle
    96.6 %; the t/z-scaled bootstrap of the raw maximum gave 97.0/96.7/98.3/98.3/97.0)."""
    cov = _path_coverage(1000, N_BOOT)
    assert all(0.92 <= cov[k] <= 0.98 for k in _AT), cov


@pytest.mark.exhaustive
@pytest.mark.parametrize("passes", [5, 10, 30])
def test_path_accuracy_interval_with_one_top_plane(passes):
    """One plane on top (f⁸), 1000 runs (SE 0.7 %): 95 ± 3 % at 5, 10 and 30 passes
    (measured 94.8/95.0/93.5 %, where Student's t on the true top plane alone covers
    94.6/95.3/93.3 % of the same draws; the t/z-scaled bootstrap gave 92.2/94.0/92.8 %)."""
    cov = _at_coverage("f8", 1000, passes, N_BOOT)
    assert 0.92 <= cov <= 0.98, cov


@pytest.mark.exhaustive
@pytest.mark.parametrize(("profile", "passes"), [("f4", 5), ("bow", 5), ("bow", 10)])
def test_path_accuracy_interval_near_and_at_a_tie(profile, passes):
    """A second plane 1.9 standard errors below the top at 5 passes (f⁴), where the
    restricted means tie planes the truth does not, and two planes tied (bow), 1000 runs:
    95 ± 3 % (measured f⁴ 96.9 %, bow 96.7/97.0 % at 5/10 passes; the t/z-scaled
    bootstrap gave 91.5 % on f⁴)."""
    cov = _at_coverage(profile, 1000, passes, N_BOOT)
    assert 0.92 <= cov <= 0.98, cov


#: covariance shapes of the cycles' scatter (eigenvalues): isotropic, anisotropic, near
#: one axis
_SHAPES = {"iso": (1.0, 1.0, 1.0), "aniso": (1.0, 0.5, 0.1), "line": (1.0, 0.01, 0.01)}


def _rp_truth(w) -> float:
    ml = _mean_length(np.asarray(w, np.float64))
    return float(ml + 3.0 * np.sqrt(np.sum(w) - ml**2))


def _rp_drp_coverage(shape: str, m: int, late_scale: float, runs: int) -> tuple[float, float]:
    """Coverage of RP's interval (early cycles) and of dRP's (`rp_difference` folded by
    `abs_interval`) over `runs` pairs of `m` early cycles and `m` late ones scattered
    `late_scale`× as much, with covariance shape `shape`."""
    w = np.array(_SHAPES[shape])
    rp, drp = _rp_truth(w), _rp_truth(late_scale**2 * w) - _rp_truth(w)
    rng = np.random.default_rng(11_000 + m)
    hit_rp, hit_drp = [], []
    for _ in range(runs):
        early = rng.normal(size=(m, 3)) * np.sqrt(w)
        late = late_scale * rng.normal(size=(m, 3)) * np.sqrt(w)
        _, lo, hi = rp_gaussian(early - early.mean(axis=0))
        hit_rp.append(lo <= rp <= hi)
        lo, hi = abs_interval(*rp_difference(early, late))
        hit_drp.append(lo <= drp <= hi)
    return float(np.mean(hit_rp)), float(np.mean(hit_drp))


@pytest.mark.exhaustive
@pytest.mark.parametrize("shape", list(_SHAPES))
def test_rp_and_drp_intervals_cover_over_scatter_shapes(shape):
    """RP and dRP at 10 and 30 cycles per group, 1000 runs each (SE 0.7 %), the late
    scatter 1×, 1.5× and 3× the early one (dRP 0, ~2 and ~6 standard errors from 0 at 10
    cycles): within 95 ± 3 %. Measured over the three shapes: RP 94.8–95.7 %, dRP
    93.4–97.1 %; with the plug-in Satterthwaite ν and the folded dRP interval they
    replaced (same draws) RP 93.9–97.1 %, dRP 91.9–99.0 % (99.0 isotropic at 10 cycles
    and 1.5×, 91.9 anisotropic at 30 cycles and 1.5×)."""
    cov = {(m, s): _rp_drp_coverage(shape, m, s, 1000) for m in (10, 30) for s in (1.0, 1.5, 3.0)}
    assert all(0.92 <= c <= 0.98 for pair in cov.values() for c in pair), cov
