"""Path deviation against brute-force references, on paths that cross and run parallel."""

import numpy as np
import pytest

import robtraj
from robtraj.analysis import commanded_path, path_deviation, point_segment
from robtraj.analysis._quat import quat_multiply, rotation_angle, slerp
from robtraj.recording import Pose, Program

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def program(points, motion=None, quats=None) -> Program:
    points = np.asarray(points, float)
    n = points.shape[0]
    q = np.tile(IDENTITY, (n, 1)) if quats is None else np.asarray(quats, float)
    motion = np.array(["start"] + ["linear"] * (n - 1) if motion is None else motion)
    return Program(Pose(points, q), motion, np.full(n, 0.1))


def brute_force(points, ref, lo=0, hi=None):
    """Nearest point on intervals [lo, hi) of the reference polyline, by checking all of them."""
    a = ref.position[lo : (hi if hi is not None else ref.n_samples - 1)]
    b = ref.position[lo + 1 : (hi + 1 if hi is not None else ref.n_samples)]
    d = np.empty((points.shape[0], a.shape[0]))
    t = np.empty_like(d)
    for r in range(a.shape[0]):  # test reference: a plain loop over segments
        n = b[r] - a[r]
        tt = np.clip((points - a[r]) @ n / (n @ n), 0.0, 1.0)
        foot = a[r] + tt[:, None] * n
        d[:, r] = np.linalg.norm(points - foot, axis=1)
        t[:, r] = tt
    j = np.argmin(d, axis=1)
    rows = np.arange(points.shape[0])
    foot = a[j] + t[rows, j][:, None] * (b[j] - a[j])
    progress = ref.progress[lo + j] + t[rows, j] * np.diff(ref.progress)[lo + j]
    return d[rows, j], foot, progress


def along(ref, s):
    return np.column_stack([np.interp(s, ref.progress, ref.position[:, i]) for i in range(3)])


def test_point_segment_matches_dense_sampling():
    rng = np.random.default_rng(0)
    p, a, b = rng.normal(size=(3, 500, 3))
    t, d = point_segment(p, a, b)
    u = np.linspace(0, 1, 20001)
    pts = a[:, None] + u[None, :, None] * (b - a)[:, None]
    dd = np.linalg.norm(pts - p[:, None], axis=2)
    assert np.allclose(d, dd.min(axis=1), atol=1e-7)
    assert np.allclose(t, u[np.argmin(dd, axis=1)], atol=1e-4)
    t0, d0 = point_segment(p[:3], a[:3], a[:3])  # degenerate segment: distance to the point
    assert np.allclose(d0, np.linalg.norm(p[:3] - a[:3], axis=1)) and np.all(t0 == 0)


def test_commanded_path_sampling():
    prog = program([[0, 0, 0], [0.1, 0, 0], [0.1, 0.05, 0], [0.1, 0.05, 0]],
                   motion=["start", "linear", "joint", "linear"])  # fmt: skip
    ref = commanded_path(prog, 0.003)
    assert np.max(np.diff(ref.progress)) <= 0.003 + 1e-12
    assert np.isclose(ref.progress[-1], 0.15)
    for target in prog.targets.position:  # move end points are samples
        assert np.min(np.linalg.norm(ref.position - target, axis=1)) < 1e-12
    assert set(ref.interval_target[~ref.interval_on_path]) == {2}
    assert np.all(ref.interval_on_path[ref.interval_target != 2])
    with pytest.raises(robtraj.UserError, match="at least two"):
        commanded_path(program([[0, 0, 0]]), 0.001)


def test_unconstrained_equals_brute_force_on_random_polyline():
    rng = np.random.default_rng(1)
    prog = program(np.cumsum(rng.normal(0, 0.02, (12, 3)), axis=0))
    ref = commanded_path(prog, 0.002)
    pts = along(ref, np.sort(rng.uniform(0, ref.progress[-1], 400))) + rng.normal(0, 1e-3, (400, 3))
    quat = np.tile(IDENTITY, (400, 1))
    res = path_deviation(ref, pts, quat, monotone=False, k=8)
    d, foot, _ = brute_force(pts, ref)
    assert np.allclose(res.distance, d, atol=1e-12)
    assert np.allclose(np.linalg.norm(res.deviation, axis=1), d, atol=1e-12)
    assert np.allclose(res.foot, foot, atol=1e-9)


def _check_monotone_against_true_pass(ref, pts, quat, true_s, pass_intervals, expect_jumps):
    free = path_deviation(ref, pts, quat, monotone=False)
    res = path_deviation(ref, pts, quat)
    # the unconstrained match is the global nearest point...
    d_all, _, _ = brute_force(pts, ref)
    assert np.allclose(free.distance, d_all, atol=1e-12)
    # ...which for some frames lies on the wrong pass; the monotone match is right everywhere
    wrong_free = np.abs(free.progress - true_s) > 0.01
    assert wrong_free.sum() >= expect_jumps
    assert np.all(np.abs(res.progress - true_s) < 0.005)
    for lo, hi in pass_intervals:
        sel = (true_s >= ref.progress[lo]) & (true_s <= ref.progress[hi])
        d, foot, s = brute_force(pts[sel], ref, lo, hi)
        assert np.allclose(res.distance[sel], d, atol=1e-12)
        assert np.allclose(res.foot[sel], foot, atol=1e-9)
        assert np.allclose(res.progress[sel], s, atol=1e-9)
    assert np.array_equal(res.jumped, wrong_free)
    assert not res.held.any()
    return res


def test_bowtie_crossing():
    # a bowtie (figure-eight of straight lines): the path crosses itself at the origin
    prog = program([[-0.1, -0.05, 0], [0.1, 0.05, 0], [0.1, -0.05, 0], [-0.1, 0.05, 0]])
    ref = commanded_path(prog, 0.0005)
    true_s = np.linspace(0, ref.progress[-1], 1500)
    pts = along(ref, true_s)
    rng = np.random.default_rng(2)
    pts += rng.normal(0, 5e-5, pts.shape)
    # on the first pass near the crossing, the robot deviates 2 mm towards the second pass
    first = (true_s < ref.progress[-1] / 3) & (np.linalg.norm(pts, axis=1) < 0.01)
    pts[first] += 0.002 * np.array([0.0, -1.0, 0.0])
    quat = np.tile(IDENTITY, (pts.shape[0], 1))
    n1 = int(np.flatnonzero(ref.interval_target == 1)[-1]) + 1
    n3 = int(np.flatnonzero(ref.interval_target == 3)[0])
    _check_monotone_against_true_pass(
        ref, pts, quat, true_s, [(0, n1), (n3, ref.n_samples - 1)], expect_jumps=3
    )


def test_parallel_passes_5mm_apart():
    # out along x, 5 mm step in y, back along x: two passes 5 mm apart
    prog = program([[0, 0, 0], [0.2, 0, 0], [0.2, 0.005, 0], [0, 0.005, 0]])
    ref = commanded_path(prog, 0.0005)
    true_s = np.linspace(0, ref.progress[-1], 1200)
    pts = along(ref, true_s)
    # on the way out the robot sags 3 mm towards the return pass in the middle third
    out = (true_s > 0.07) & (true_s < 0.13)
    pts[out, 1] += 0.003
    quat = np.tile(IDENTITY, (pts.shape[0], 1))
    n1 = int(np.flatnonzero(ref.interval_target == 1)[-1]) + 1
    n3 = int(np.flatnonzero(ref.interval_target == 3)[0])
    res = _check_monotone_against_true_pass(
        ref, pts, quat, true_s, [(0, n1), (n3, ref.n_samples - 1)], expect_jumps=out.sum()
    )
    assert np.allclose(res.distance[out], 0.003, atol=1e-9)
    assert np.array_equal(res.jumped, out)


def test_orientation_error_at_foot_point():
    qs = np.array([[1.0, 0, 0, 0], [np.cos(0.4), 0, 0, np.sin(0.4)], [np.cos(0.4), 0.3, 0, 0.4]])
    qs[2] /= np.linalg.norm(qs[2])
    prog = program([[0, 0, 0], [0.1, 0, 0], [0.1, 0, 0]], quats=qs)  # last move turns in place
    ref = commanded_path(prog, 0.001)
    s = np.linspace(0.0, 0.099, 300)  # (at 0.1 the turn in place begins)
    pts = along(ref, s) + [0, 0.001, 0]
    q_cmd = slerp(np.tile(qs[0], (300, 1)), np.tile(qs[1], (300, 1)), s / 0.1)
    extra = np.array([np.cos(0.005), np.sin(0.005), 0, 0])  # 0.01 rad about x
    q_meas = quat_multiply(q_cmd, np.tile(extra, (300, 1)))
    res = path_deviation(ref, pts, q_meas)
    assert np.allclose(res.orientation_error, 0.01, atol=1e-9)
    assert np.allclose(res.distance, 0.001, atol=1e-12)
    # turning in place: the foot point's orientation is the nearest one on the arc
    q_half = slerp(qs[1], qs[2], 0.37)
    tail = path_deviation(
        ref, np.tile([0.1, 0, 0], (5, 1)), np.tile(q_half, (5, 1)), monotone=False
    )
    assert np.allclose(tail.orientation_error, 0.0, atol=1e-7)
    # stable near zero
    tiny = np.array([np.cos(5e-10), np.sin(5e-10), 0, 0])
    assert np.isclose(rotation_angle(IDENTITY, tiny), 1e-9, rtol=1e-6)


def test_a_turn_in_place_is_matched_by_orientation():
    """At a corner the program turns in place through two orientations (two zero-length
    moves) before the next move. The robot dwells there while it turns, its position
    noisy by 20 µm (so its foot point falls before, on and after the corner) and its
    orientation 0.01 rad about x off the commanded turn: the orientation error is 0.01 rad
    at every frame of the dwell, as along the moves, and the distances are those of the
    position match alone. Without the turn window (`turn_window=0`) frames whose foot
    falls just before the corner are compared with the incoming move's orientation."""
    rng = np.random.default_rng(5)
    qs = np.array([IDENTITY, IDENTITY, [np.cos(0.4), 0, 0, np.sin(0.4)],
                   [np.cos(0.3), 0, np.sin(0.3), 0], [np.cos(0.3), 0, np.sin(0.3), 0]])  # fmt: skip
    corner = [0.1, 0, 0]
    prog = program([[0, 0, 0], corner, corner, corner, [0.1, 0.1, 0]], quats=qs)
    ref = commanded_path(prog, 0.0005)
    n = 400
    approach = along(ref, np.linspace(0, 0.0995, n))
    dwell = np.tile(corner, (2 * n, 1)) + rng.normal(0, 2e-5, (2 * n, 3))
    leave = along(ref, np.linspace(0.1005, 0.2, n))
    pts = np.concatenate([approach, dwell, leave])
    u = np.linspace(0, 1, n)
    q_cmd = np.concatenate([
        np.tile(IDENTITY, (n, 1)),
        slerp(np.tile(qs[1], (n, 1)), np.tile(qs[2], (n, 1)), u),
        slerp(np.tile(qs[2], (n, 1)), np.tile(qs[3], (n, 1)), u),
        np.tile(qs[4], (n, 1)),
    ])  # fmt: skip
    q_meas = q_cmd
    res = path_deviation(ref, pts, q_meas)
    np.testing.assert_allclose(res.orientation_error, 0.0, atol=1e-7)
    position_only = path_deviation(ref, pts, q_meas, turn_window=0.0)
    np.testing.assert_array_equal(res.distance, position_only.distance)
    np.testing.assert_array_equal(res.progress, position_only.progress)
    assert position_only.orientation_error.max() > 0.2


def test_nan_frames_and_summary():
    prog = program([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0]], motion=["start", "linear", "joint"])
    ref = commanded_path(prog, 0.001)
    pts = along(ref, np.linspace(0, 0.2, 200)) + [0, 0, 0.002]
    pts[50] = np.nan
    res = path_deviation(ref, pts, np.tile(IDENTITY, (200, 1)))
    assert np.isnan(res.distance[50]) and res.interval[50] == -1
    summ = res.summary()
    assert summ.n == int(np.sum(res.on_path)) and np.isclose(summ.distance_rms, 0.002)
    assert summ.n < res.summary(include_joint_moves=True).n
    assert set(summ.to_json()) >= {"distance_max_mm", "orientation_rms_deg"}
