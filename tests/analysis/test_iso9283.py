"""ISO 9283 characteristics against a direct NumPy implementation of the standard's formulas,
on a synthetic cube test with known injected errors."""

import json

import numpy as np
import pytest
from _synthetic import attained, cube_program, quat, round_corners, trajectory
from scipy.spatial.transform import Rotation

import robtraj
from robtraj.analysis import iso9283
from robtraj.analysis.iso9283 import pose_statistics
from robtraj.recording import Pose, Program

CYCLES, PATH_CYCLES = 30, 6
OFFSET = np.array([0.8e-3, -0.5e-3, 0.3e-3])  # [m] constant pose error
SIGMA = 0.1e-3  # [m] per-axis scatter per cycle
ROT_OFFSET = np.array([1e-3, -0.5e-3, 0.0])  # [rad] constant orientation error (base frame)
ROT_SIGMA = 2e-4  # [rad]


@pytest.fixture(scope="module")
def cube():
    rng = np.random.default_rng(7)
    prog, dwell = cube_program(CYCLES, PATH_CYCLES)
    pos, q = attained(prog, OFFSET, SIGMA, ROT_OFFSET, ROT_SIGMA, rng)
    t, p, qq, seg = trajectory(prog, pos, q, dwell, speed_scale=0.95)
    res = iso9283(prog, t, p, qq, segment=seg)
    return prog, dwell, pos, q, res


def rp_direct(x):
    """ISO 9283 §7.2.2 written out: l_j = |x_j − x̄|, RP = l̄ + 3·sqrt(Σ(l_j − l̄)²/(n−1))."""
    bary = x.mean(axis=0)
    l = np.sqrt(((x - bary) ** 2).sum(axis=1))
    return l.mean() + 3.0 * np.sqrt(((l - l.mean()) ** 2).sum() / (len(l) - 1))


def test_pose_accuracy_and_repeatability(cube):
    prog, dwell, pos, q, res = cube
    tp = prog.targets.position
    assert len(res.poses) == 5
    for pose in res.poses:
        same = np.flatnonzero(np.all(np.isclose(tp, pose.commanded_position), axis=1) & dwell)
        same = same[same > 0]  # the start target is not attained by a move
        x = pos[same]  # what the robot attained at that pose, cycle by cycle
        q_att = q[same]
        assert pose.n_cycles == CYCLES == x.shape[0]
        # AP: barycentre minus command, formula by formula
        ap = x.mean(axis=0) - pose.commanded_position
        assert np.allclose(pose.AP_xyz, ap, atol=1e-12)
        assert np.isclose(pose.AP, np.sqrt((ap**2).sum()), atol=1e-12)
        assert np.isclose(pose.RP, rp_direct(x), atol=1e-12)
        # AP equals the injected constant offset within its sampling error σ/√n (4σ bound)
        assert np.all(np.abs(pose.AP_xyz - OFFSET) < 4 * SIGMA / np.sqrt(CYCLES))
        # orientation: a, b, c of R_att·R_cmdᵀ; mean = APa.., 3·S = RPa..
        abc = (
            Rotation.from_quat(q_att[:, [1, 2, 3, 0]])
            * Rotation.from_quat(pose.commanded_quaternion_wxyz[[1, 2, 3, 0]]).inv()
        ).as_euler("xyz")
        assert np.allclose(pose.AP_abc, abc.mean(axis=0), atol=1e-12)
        assert np.allclose(pose.RP_abc, 3 * abc.std(axis=0, ddof=1), atol=1e-12)
        assert np.all(np.abs(pose.AP_abc - ROT_OFFSET) < 4 * ROT_SIGMA / np.sqrt(CYCLES) + 1e-6)
        assert np.isclose(pose.AP_angle, np.linalg.norm(ROT_OFFSET), atol=4 * ROT_SIGMA)


def test_rp_matches_injected_scatter():
    """RP over many poses vs its sampling distribution for n = 30 cycles of N(0, σ²I)."""
    rng = np.random.default_rng(3)
    sims = np.array([rp_direct(rng.normal(0, SIGMA, (CYCLES, 3))) for _ in range(4000)])
    expected, spread = sims.mean(), sims.std()
    # true value: l ~ σ·χ₃, mean 2σ√(2/π), sd σ√(3 − 8/π); the estimator's bias is small
    true_rp = SIGMA * (2 * np.sqrt(2 / np.pi) + 3 * np.sqrt(3 - 8 / np.pi))
    assert abs(expected - true_rp) < 0.1 * true_rp
    prog, dwell = cube_program(CYCLES, 0)
    rps = []
    for seed in range(3):
        pos, q = attained(prog, OFFSET, SIGMA, ROT_OFFSET, 0.0, np.random.default_rng(seed))
        t, p, qq, seg = trajectory(prog, pos, q, dwell)
        rps += [pose.RP for pose in iso9283(prog, t, p, qq, segment=seg).poses]
    # 15 RP values, each with the spread above: their mean is within 4·spread/√15
    assert abs(np.mean(rps) - expected) < 4 * spread / np.sqrt(len(rps))


def test_distance_accuracy(cube):
    prog, dwell, pos, q, res = cube
    tp = prog.targets.position
    assert len(res.distances) == 5
    for d in res.distances:
        # consecutive pose-test targets with the commanded distance of this pair
        js = [j for j in range(2, len(tp)) if dwell[j] and dwell[j - 1]
              and np.isclose(np.linalg.norm(tp[j] - tp[j - 1]), d.commanded)]  # fmt: skip
        pairs = {}
        for j in js:
            pairs.setdefault((tuple(tp[j - 1]), tuple(tp[j])), []).append(j)
        for js_pair in pairs.values():
            dd = np.array([np.linalg.norm(pos[j] - pos[j - 1]) for j in js_pair])
            if len(dd) == d.n and np.isclose(dd.mean() - d.commanded, d.AD, atol=1e-12):
                assert np.isclose(d.RD, 3 * dd.std(ddof=1), atol=1e-12)
                break
        else:
            pytest.fail(f"no direct AD matches {d.name}")


def test_path_accuracy_velocity_corners(cube):
    prog, dwell, pos, q, res = cube
    tp = prog.targets.position
    assert len(res.paths) == 4 and len(res.corners) == 4
    first_rect = int(np.flatnonzero(prog.motion == "linear")[0])
    for k, path in enumerate(res.paths):
        j0 = first_rect + k
        occ = [j0 + 4 * c for c in range(PATH_CYCLES)]
        c0, c1 = tp[j0 - 1], tp[j0]
        n = (c1 - c0) / np.linalg.norm(c1 - c0)
        f = path.plane_fraction
        cmd = c0 + f[:, None] * (c1 - c0)
        # each pass is a straight line between attained corners: cut it with the normal planes
        x = np.empty((len(occ), f.size, 3))
        for o, j in enumerate(occ):
            a, b = pos[j - 1], pos[j]
            u = ((cmd - a) @ n) / ((b - a) @ n)
            x[o] = a + u[:, None] * (b - a)
        bary = x.mean(axis=0)
        at = np.linalg.norm(bary - cmd, axis=1)
        l = np.linalg.norm(x - bary, axis=2)
        rt = l.mean(axis=0) + 3 * l.std(axis=0, ddof=1)
        assert np.allclose(path.plane_AT, at, atol=1e-9)
        assert np.allclose(path.plane_RT, rt, atol=1e-9)
        assert np.isclose(path.AT, at.max(), atol=1e-9) and np.isclose(path.RT, rt.max(), atol=1e-9)
        assert path.n_cycles == PATH_CYCLES
        # the robot ran at 95 % of the commanded speed, steadily
        assert np.isclose(path.AV, -0.05, atol=1e-6)
        assert abs(path.RV) < 1e-6 and path.FV < 1e-6
    for corner in res.corners:  # the measured path passes through the attained corners
        assert corner.n >= PATH_CYCLES - 1
        assert corner.CR_max < np.linalg.norm(OFFSET) + 5 * SIGMA


def test_to_json_is_plain_json(cube):
    out = json.loads(json.dumps(cube[-1].to_json()))
    p1 = out["poses"]["P1"]
    assert {"AP_mm", "RP_mm", "APa_deg", "RPc_deg", "AP_angle_deg", "dAP_mm"} <= set(p1)
    assert p1["vAP_mm"] is None  # each pose is approached from one direction only
    assert {"AT_mm", "RT_mm", "AV_percent", "FV_mm_per_s"} <= set(next(iter(out["paths"].values())))
    assert {"AD_mm", "RD_mm"} <= set(next(iter(out["distances"].values())))


def test_stabilisation_and_overshoot():
    prog, dwell = cube_program(4, 0)
    pos, q = attained(prog, OFFSET, 0.0, ROT_OFFSET, 0.0, np.random.default_rng(0))
    rate, band, amp, tau, freq = 500.0, 1e-4, 5e-4, 0.1, 5.0
    t, p, qq, seg = trajectory(prog, pos, q, dwell, rate=rate, dwell_time=2.0)
    # a damped ringing of 0.5 mm along x after every arrival (τ = 0.1 s, 5 Hz)
    still = np.concatenate([[False], np.all(np.diff(p, axis=0) == 0, axis=1)])
    arrive = np.flatnonzero(np.diff(still.astype(int)) == 1)  # first frame at the target
    ring = np.zeros(t.size)
    for i in arrive:
        dt = t[i:] - t[i]
        ring[i:] += np.where(dt < 1.0, amp * np.exp(-dt / tau) * np.sin(2 * np.pi * freq * dt), 0)
    p = p + ring[:, None] * [1.0, 0, 0]
    res = iso9283(prog, t, p, qq, segment=seg, band=band, min_dwell=0.5)
    # truth from the continuous ringing: the peak at tan(ωt) = ωτ; the last time outside
    # the band on a 1 µs grid. The approach at 0.2 m/s enters the band at the arrival
    # frame, so the measurement is the truth up to one frame (1/rate) of sampling.
    w = 2 * np.pi * freq
    t_peak = np.arctan(w * tau) / w
    overshoot = amp * np.exp(-t_peak / tau) * np.sin(w * t_peak)
    fine = np.arange(0.0, 1.0, 1e-6)
    t_stab = fine[np.flatnonzero(amp * np.exp(-fine / tau) * np.abs(np.sin(w * fine)) > band)[-1]]
    for pose in res.poses:
        assert abs(pose.t_stab_mean - t_stab) <= 1.0 / rate + 1e-9  # < 10 % of t_stab
        assert abs(pose.t_stab_max - t_stab) <= 1.0 / rate + 1e-9
        # a sampled peak is low by at most amp·(ω/rate)²/8 (0.2 % here; 10 % is allowed)
        assert 0 <= overshoot - pose.overshoot_max <= amp * (w / rate) ** 2 / 8
        assert abs(pose.overshoot_mean - overshoot) < 0.1 * overshoot
        lo, hi = pose.ci["t_stab_mean"]
        assert lo <= pose.t_stab_mean <= hi


def _rp_sd(m: int, rng) -> float:
    """Standard deviation of RP over m cycles of N(0, I₃), by simulation."""
    x = rng.normal(size=(4000, m, 3))
    l = np.linalg.norm(x - x.mean(axis=1, keepdims=True), axis=2)
    return float(np.std(l.mean(1) + 3 * l.std(1, ddof=1)))


def test_vap_and_drift_recovered_from_injected_truth():
    """Each pose approached from two directions with an error B along the approach, a
    drift D per cycle, and N(0, σ²) scatter; vAP and dAP against their injected values."""
    rng = np.random.default_rng(11)
    prog, dwell = cube_program(CYCLES, 0, alternate=True)
    tp = prog.targets.position
    u = np.zeros_like(tp)
    u[1:] = np.diff(tp, axis=0) / np.linalg.norm(np.diff(tp, axis=0), axis=1, keepdims=True)
    cycle = np.maximum(np.arange(len(tp)) - 1, 0) // 5
    approach_error, drift = 0.2e-3, np.array([10e-6, -5e-6, 0.0])  # [m], [m per cycle]
    truth_err = OFFSET + approach_error * u + drift * cycle[:, None]
    pos, q = attained(prog, truth_err, SIGMA, ROT_OFFSET, ROT_SIGMA, rng)
    t, p, qq, seg = trajectory(prog, pos, q, dwell)
    res = iso9283(prog, t, p, qq, segment=seg)
    m = CYCLES // 3
    for pose in res.poses:
        js = np.flatnonzero(np.all(np.isclose(tp, pose.commanded_position), axis=1))
        js = js[js > 0]  # the start target is not attained by a move
        dirs = np.unique(np.round(u[js], 9), axis=0)
        assert len(dirs) == 2 and len(js) == CYCLES
        e = truth_err[js]
        first = np.all(np.isclose(u[js], dirs[0]), axis=1)
        vap = np.linalg.norm(e[first].mean(0) - e[~first].mean(0))
        dap = abs(np.linalg.norm(e[-m:].mean(0)) - np.linalg.norm(e[:m].mean(0)))
        # two barycentres of 15 cycles each: σ·√(2/15) per axis; 4σ (≈ 6e-5 two-sided)
        assert abs(pose.vAP - vap) < 4 * SIGMA * np.sqrt(2 / 15), (pose.vAP, vap)
        assert abs(pose.dAP - dap) < 4 * SIGMA * np.sqrt(2 / m), (pose.dAP, dap)


def test_drp_recovered_from_injected_truth():
    """Late cycles scatter 2× as much as early ones: dRP = RP(2σ) − RP(σ)."""
    rng = np.random.default_rng(12)
    prog, dwell = cube_program(CYCLES, 0)
    n_t = len(prog.targets.position)
    late = np.arange(n_t) > 1 + 5 * (CYCLES - CYCLES // 3)
    sigma = np.where(late, 2 * SIGMA, SIGMA)[:, None]
    pos = prog.targets.position + OFFSET + sigma * rng.normal(size=(n_t, 3))
    _, q = attained(prog, OFFSET, 0.0, ROT_OFFSET, ROT_SIGMA, rng)
    t, p, qq, seg = trajectory(prog, pos, q, dwell)
    res = iso9283(prog, t, p, qq, segment=seg)
    m = CYCLES // 3
    # RP of N(0, σ²I) is σ·(2√(2/π) + 3√(3 − 8/π)) up to the barycentre's O(1/m) shrinkage
    per_sigma = 2 * np.sqrt(2 / np.pi) + 3 * np.sqrt(3 - 8 / np.pi)
    drp = (2 * SIGMA - SIGMA) * per_sigma
    tol = 4 * SIGMA * _rp_sd(m, rng) * np.sqrt(1 + 2**2)
    for pose in res.poses:
        assert abs(pose.dRP - drp) < tol, (pose.dRP, drp, tol)


def test_corner_round_off_and_overshoot_recovered():
    """Corners cut by an arc of radius ρ (CR = ρ(√2 − 1)), then a bump of height h out
    beyond the second leg, δ(s) = h·sin(π(s − 2ρ)/ℓ) for s ∈ [2ρ, 2ρ + ℓ] along it
    (CO = h, larger than any deviation of the arc)."""
    prog, dwell = cube_program(2, 4)
    pos, q = prog.targets.position, prog.targets.quaternion_wxyz
    rate, radius, h, bump = 1000.0, 2e-3, 5e-3, 0.04
    t, p, qq, seg = trajectory(prog, pos, q, dwell, rate=rate)
    p = round_corners(prog, t, p, seg, radius)
    tp, lin = prog.targets.position, prog.motion == "linear"
    for j in range(1, len(tp) - 1):
        if lin[j] and lin[j + 1]:
            d1 = (tp[j] - tp[j - 1]) / np.linalg.norm(tp[j] - tp[j - 1])
            d2 = (tp[j + 1] - tp[j]) / np.linalg.norm(tp[j + 1] - tp[j])
            s = (p[seg == j + 1] - tp[j]) @ d2 - 2 * radius
            on = (s > 0) & (s < bump)
            idx = np.flatnonzero(seg == j + 1)[on]
            p[idx] += h * np.sin(np.pi * s[on] / bump)[:, None] * d1
    res = iso9283(prog, t, p, qq, segment=seg)
    assert len(res.corners) == 4
    # frames 0.2 mm apart: the closest one misses the arc's closest point by ≤ 0.1 mm
    # along it, i.e. by ≤ (0.1 mm)²/(2ρ) in distance; the bump's sampled peak is low by
    # ≤ h·(π·0.1 mm/ℓ)²/2
    step = 0.2 / rate
    for corner in res.corners:
        assert abs(corner.CR_mean - radius * (np.sqrt(2) - 1)) <= step**2 / (8 * radius), corner
        assert abs(corner.CR_max - radius * (np.sqrt(2) - 1)) <= step**2 / (8 * radius)
        assert -1e-12 <= h - corner.CO_mean <= h * (np.pi * step / 2 / bump) ** 2 / 2, corner
        assert -1e-12 <= h - corner.CO_max <= h * (np.pi * step / 2 / bump) ** 2 / 2


def test_velocity_characteristics_recovered():
    """Each pass at its own speed (scale 0.97 + N(0, 0.02²)) with a 3 % ripple at 4 Hz:
    AV, RV and FV against the injected speeds."""
    rng = np.random.default_rng(5)
    prog, dwell = cube_program(2, 8)
    n_t = len(prog.targets.position)
    scale = 0.97 + 0.02 * rng.normal(size=n_t)
    a, f, rate, window = 0.03, 4.0, 200.0, 0.05
    t, p, qq, seg = trajectory(
        prog, prog.targets.position, prog.targets.quaternion_wxyz, dwell, rate=rate,
        speed_scale=scale, ripple=(a, f),
    )  # fmt: skip
    res = iso9283(prog, t, p, qq, segment=seg, speed_window=window)
    first_rect = int(np.flatnonzero(prog.motion == "linear")[0])
    for k, path in enumerate(res.paths):  # in the order of the rectangle's legs
        vc = path.commanded_speed
        occ = [first_rect + k + 4 * c for c in range(8)]
        v = scale[occ] * vc  # injected mean speed of each pass (whole ripple periods)
        # the mean steady speed per pass is v exactly; AV, RV are their mean and 3·S
        assert np.isclose(path.AV, v.mean() / vc - 1, atol=2e-3), (path.AV, v.mean() / vc - 1)
        assert np.isclose(path.RV, 3 * v.std(ddof=1) / vc, rtol=0.05, atol=2e-3)
        # a sinusoid of amplitude a·v seen through a central difference over ±h has
        # amplitude a·v·sin(ωh)/(ωh); FV = max over passes of (max − min), frames sample the
        # extremes to within 1 − cos(ω/2rate) of the amplitude (< 0.3 %)
        lengths = np.linalg.norm(prog.targets.position[occ] - prog.targets.position[
            np.array(occ) - 1], axis=1)  # fmt: skip
        durs = lengths / v
        w = 4 * np.pi * np.maximum(np.round(f * durs / 2), 1) / durs
        fv = np.max(2 * a * v * np.sin(w * window / 2) / (w * window / 2))
        assert abs(path.FV - fv) < 0.01 * fv, (path.FV, fv)
        lo, hi = path.ci["AV"]
        assert lo <= path.AV <= hi


def test_errors():
    prog, dwell = cube_program(3, 0)
    one = Program(Pose(prog.targets.position[:1], prog.targets.quaternion_wxyz[:1]),
                  prog.motion[:1], prog.speed[:1])  # fmt: skip
    t = np.arange(10.0)
    with pytest.raises(robtraj.UserError, match="at least two targets"):
        iso9283(one, t, np.zeros((10, 3)), np.tile([1.0, 0, 0, 0], (10, 1)))
    pos, q = attained(prog, OFFSET, 0.0, ROT_OFFSET, 0.0, np.random.default_rng(0))
    t, p, qq, seg = trajectory(prog, pos, q, np.zeros_like(dwell))  # never stops
    with pytest.raises(robtraj.UserError, match="no ISO 9283 cycles"):
        iso9283(prog, t, p, qq, segment=seg)


def test_cli_table_prints_intervals_and_warns_below_30_cycles(cube, capsys):
    from robtraj.cli._iso9283 import print_table

    res = cube[-1]
    print_table(res)
    out, err = capsys.readouterr()
    assert f"pose P1: {CYCLES} cycles" in out
    # every characteristic with an interval in the JSON is printed with it
    ap = [line for line in out.splitlines() if line.split()[:1] == ["AP"]]
    lo, hi = res.poses[0].to_json()["AP_mm_ci95"]
    assert ap and f"[{lo:.4g}, {hi:.4g}]" in ap[0]
    n_ci = sum(k.endswith("_ci95") for block in res.to_json().values()
               for d in block.values() for k in d)  # fmt: skip
    assert out.count("95 % CI") == n_ci
    # the pose test has the standard's 30 cycles, the path test 6: only the paths warn
    assert "warning: fewer than the standard's 30 cycles" in err
    assert f"({PATH_CYCLES})" in err and "P1 (" not in err


def test_json_intervals_next_to_values(cube):
    out = json.loads(json.dumps(cube[-1].to_json()))
    p1 = out["poses"]["P1"]
    for key in ["AP_mm", "RP_mm", "APx_mm", "RPa_deg", "AP_angle_deg", "RP_angle_deg"]:
        lo, hi = p1[f"{key}_ci95"]
        assert lo <= p1[key] <= hi or key in ("RP_mm", "RP_angle_deg"), key
        assert lo < hi
    assert p1["t_stab_max_s_ci95"] is None  # a maximum over cycles has no interval
    path = next(iter(out["paths"].values()))
    assert path["AV_percent_ci95"] is not None and path["FV_mm_per_s_ci95"] is None


#: characteristics that may be negative (signed means); AV is ≥ −1, AD ≥ −D_c
_SIGNED = ("APx", "APy", "APz", "APa", "APb", "APc", "AD", "AV")


def _below_bounds(doc) -> list[tuple[str, str, str, float]]:
    """Intervals of an ISO JSON doc that start below their quantity's physical range: 0
    for the non-negative characteristics, −100 % for AV."""
    out = []
    for block, items in doc.items():
        for name, d in items.items():
            for key, ci in d.items():
                if not key.endswith("_ci95") or ci is None:
                    continue
                k = key[: -len("_ci95")]
                floor = -100.0 if k.startswith("AV") else 0.0
                if ci[0] < floor and (k.startswith("AV") or not k.startswith(_SIGNED)):
                    out.append((block, name, k, ci[0]))
    return out


def _few_cycle_run(seed: int):
    """Three pose cycles (as the demo) with a ringing after each arrival whose amplitude
    varies from cycle to cycle (0, 0.2 or 0.8 mm: some cycles never leave the 0.1 mm
    band, t_stab = OV = 0) and a pose error near 0; three passes of the rectangle with
    corners cut by a 2 mm arc and 0.3 mm of noise per frame (CR, CO vary by pass)."""
    rng = np.random.default_rng(seed)
    prog, dwell = cube_program(3, 3)
    pos, q = attained(prog, np.full(3, 2e-6), 2e-6, np.zeros(3), 1e-5, rng)
    t, p, qq, seg = trajectory(prog, pos, q, dwell, rate=200.0, dwell_time=1.5)
    still = np.concatenate([[False], np.all(np.diff(p, axis=0) == 0, axis=1)])
    ring = np.zeros(t.size)
    for i in np.flatnonzero(np.diff(still.astype(int)) == 1):
        dt, amp = t[i:] - t[i], rng.choice([0.0, 2e-4, 8e-4])
        ring[i:] += np.where(dt < 1.0, amp * np.exp(-dt / 0.1) * np.sin(10 * np.pi * dt), 0)
    p = round_corners(prog, t, p + ring[:, None] * [1.0, 0, 0], seg, 2e-3)
    p[prog.motion[seg] == "linear"] += rng.normal(
        0.0, 3e-4, (np.sum(prog.motion[seg] == "linear"), 3)
    )
    return prog, t, p, qq, seg


def test_intervals_of_non_negative_characteristics_stay_at_or_above_zero(monkeypatch):
    """On simulated three-cycle runs every interval of a non-negative characteristic
    (lengths, RP/RT, stabilisation time, overshoot, CR/CO, speeds, drift) starts at 0 or
    above, AV's at −100 % or above; without the cut (`bounded` as the identity) the
    Student-t intervals of the means reach below 0 on the same runs."""
    import sys

    runs = [_few_cycle_run(seed) for seed in (21, 22)]
    docs = [iso9283(*r[:4], segment=r[4], band=1e-4, min_dwell=0.5).to_json() for r in runs]
    for doc in docs:
        assert doc["poses"] and doc["paths"] and doc["corners"]
        assert not _below_bounds(doc), _below_bounds(doc)
    for mod in (
        "robtraj.analysis.iso9283",
        "robtraj.analysis._iso_path",
        "robtraj.analysis._iso_ci",
    ):
        monkeypatch.setattr(sys.modules[mod], "bounded", lambda ci, *_: ci)
    uncut = [iso9283(*r[:4], segment=r[4], band=1e-4, min_dwell=0.5).to_json() for r in runs]
    below = {k for doc in uncut for _, _, k, _ in _below_bounds(doc)}
    assert {"t_stab_mean_s", "OV_mean_mm"} <= below, below


def test_pose_intervals_of_lengths_stay_at_or_above_zero():
    """Lengths near 0 (AP, AP_angle, vAP, dAP, dRP with no true error, 4 cycles): the
    studentised bootstrap and the folded intervals start at 0 or above, in 100 runs."""
    rng = np.random.default_rng(8)
    cp, cq = np.array([1.0, 0.0, 0.5]), np.array([1.0, 0.0, 0.0, 0.0])
    for _ in range(100):
        x = cp + rng.normal(0.0, SIGMA, (4, 3))
        q = quat(rng.normal(0.0, ROT_SIGMA, (4, 3)))
        _, ci = pose_statistics(x, q, cp, cq, np.arange(4) % 2, 2, rng, 200)
        for k in ("AP", "RP", "RPa", "RPb", "RPc", "AP_angle", "RP_angle", "vAP", "dAP", "dRP"):
            assert ci[k][0] >= 0.0, (k, ci[k])


def test_smoothed_speed_by_blocks_is_the_central_difference_over_the_window():
    """Block by block (several blocks, unseen frames skipped) against the central
    difference over ±window/2 of the seen frames written out directly."""
    from robtraj.analysis._dwell import smoothed_speed

    rng = np.random.default_rng(4)
    n, window = 5003, 0.05
    time = np.cumsum(rng.uniform(0.5e-3, 1.5e-3, n))
    position = np.cumsum(rng.normal(0, 1e-5, (n, 3)), 0)
    position[rng.random(n) < 0.1] = np.nan
    ok = np.all(np.isfinite(position), axis=1)
    t, p = time[ok], position[ok]
    direct = np.full(n, np.nan)
    for k in range(t.size):
        lo = int(np.searchsorted(t, t[k] - window / 2, side="left"))
        hi = min(max(int(np.searchsorted(t, t[k] + window / 2, side="right")) - 1, 0), t.size - 1)
        lo = max(min(lo, hi - 1), 0)
        hi = min(max(hi, lo + 1), t.size - 1)
        direct[np.flatnonzero(ok)[k]] = np.linalg.norm(p[hi] - p[lo]) / (t[hi] - t[lo])
    got = smoothed_speed(time, position, window, block=700)
    np.testing.assert_allclose(got, direct, rtol=1e-14, atol=0)  # the norm's rounding
