"""ISO 9283 performance characteristics from measured TCP poses and the program.

All inputs in SI and in the robot base frame; `to_json()` gives mm, degrees, seconds
and per cent with the unit in the key. Orientation is reported both as the standard's
components a, b, c (rotations about the base x, y, z axes of the error rotation
`R_attained · R_commandedᵀ`, see `_quat.error_components`) and as the single rotation
angle of paper eq. 1–2.

Test poses and cycles come from the program: targets at the same position and
orientation are the same pose; every stationary stretch of the measurement (a dwell)
near a target is one attainment of that pose, in time order one per cycle. Poses
attained at least twice are test poses, named ``P1``, ``P2``, … in order of first
appearance in the program (pass `pose_names` to use the standard's numbering). Path
characteristics use the linear moves that are repeated (same start and end pose) and
do not join two test poses; their poses are named ``T1``, ``T2``, ….
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from jaxtyping import Float
from scipy import stats

from .._errors import UserError
from ..recording import Program
from ._dwell import Dwell, cluster_targets, find_dwells
from ._iso_ci import (
    N_BOOT,
    NAN_INTERVAL,
    Interval,
    abs_interval,
    bounded,
    length_interval,
    pair,
    rp_difference,
    rp_gaussian_interval,
    t_interval,
    three_s_interval,
    welch,
    welch_interval,
    with_intervals,
)
from ._iso_path import CornerCharacteristics, PathCharacteristics, path_characteristics
from ._quat import error_components, mean_quaternion, rotation_angle, to_rotation

_APPROACH_RADIUS = 5e-3  # [m] stabilisation/overshoot look at the approach from here on
_MIN_BAND = 1e-6  # [m] floor of the default limit band (RP = 0 for a perfect robot)


def _s(x: np.ndarray) -> float:
    """Sample standard deviation (n - 1), as the standard uses."""
    return float(np.std(x, ddof=1)) if np.size(x) > 1 else float("nan")


@dataclasses.dataclass(frozen=True)
class PoseCharacteristics:
    """Pose accuracy and repeatability of one test pose over `n_cycles` attainments.

    Positions [m], angles [rad], times [s]. `AP_xyz` = barycentre − command, `AP` its
    length, `RP` = l̄ + 3·S_l. `AP_abc` = mean of the (a, b, c) errors, `RP_abc` = 3·S per
    component; `AP_angle` is the single angle between the mean attained orientation and
    the command, `RP_angle` = mean + 3·S of the single angles to the mean orientation.
    `vAP` (multi-directional variation: largest distance between the barycentres of
    attainments from different directions) is NaN when the pose is approached from one
    direction only. `t_stab`/`overshoot`: mean and max over cycles, from the approach within 5 mm of the
    attained pose (time from first entering the limit band until staying in it, and the
    largest distance after first entering it, 0 if it never leaves). `dAP`, `dRP`: drift,
    |AP(late) − AP(early)| and |RP(late) − RP(early)| over the first and last
    `drift_cycles` cycles (NaN with fewer than 4 cycles). `ci`: 95 % intervals by
    characteristic (see `pose_statistics`); maxima over cycles have none (a sample
    extreme estimates no fixed parameter). `approach` `(n_cycles,)`: the pose each
    attainment came from.
    """

    name: str
    commanded_position: np.ndarray
    commanded_quaternion_wxyz: np.ndarray
    attained_position: np.ndarray
    attained_quaternion_wxyz: np.ndarray
    attained_time: np.ndarray
    approach: np.ndarray
    n_cycles: int
    AP_xyz: np.ndarray
    AP: float
    RP: float
    AP_abc: np.ndarray
    RP_abc: np.ndarray
    AP_angle: float
    RP_angle: float
    vAP: float
    t_stab_mean: float
    t_stab_max: float
    overshoot_mean: float
    overshoot_max: float
    dAP: float
    dRP: float
    ci: dict[str, Interval] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        mm, deg = 1e3, float(np.degrees(1.0))
        rows = [
            ("APx_mm", self.AP_xyz[0], mm), ("APy_mm", self.AP_xyz[1], mm),
            ("APz_mm", self.AP_xyz[2], mm), ("AP_mm", self.AP, mm), ("RP_mm", self.RP, mm),
            ("APa_deg", self.AP_abc[0], deg), ("APb_deg", self.AP_abc[1], deg),
            ("APc_deg", self.AP_abc[2], deg), ("AP_angle_deg", self.AP_angle, deg),
            ("RPa_deg", self.RP_abc[0], deg), ("RPb_deg", self.RP_abc[1], deg),
            ("RPc_deg", self.RP_abc[2], deg), ("RP_angle_deg", self.RP_angle, deg),
            ("vAP_mm", self.vAP, mm), ("t_stab_mean_s", self.t_stab_mean, 1.0),
            ("t_stab_max_s", self.t_stab_max, 1.0), ("OV_mean_mm", self.overshoot_mean, mm),
            ("OV_max_mm", self.overshoot_max, mm), ("dAP_mm", self.dAP, mm),
            ("dRP_mm", self.dRP, mm),
        ]  # fmt: skip
        out = {"n_cycles": self.n_cycles, "commanded_mm": (self.commanded_position * mm).tolist()}
        return out | with_intervals(rows, self.ci, {"OV_mean": "overshoot_mean"})


@dataclasses.dataclass(frozen=True)
class DistanceCharacteristics:
    """Distance accuracy `AD` = D̄ − D_c and repeatability `RD` = 3·S_D [m] between two test
    poses attained one after the other, over `n` pairs; `ci`: their 95 % intervals
    (Student t and χ²)."""

    name: str
    commanded: float
    AD: float
    RD: float
    n: int
    ci: dict[str, Interval] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        rows = [("AD_mm", self.AD, 1e3), ("RD_mm", self.RD, 1e3)]
        return {"n": self.n, "Dc_mm": self.commanded * 1e3} | with_intervals(rows, self.ci, {})


@dataclasses.dataclass(frozen=True)
class Iso9283Result:
    """All characteristics found in one recording (empty lists where a test is absent)."""

    poses: list[PoseCharacteristics]
    distances: list[DistanceCharacteristics]
    paths: list[PathCharacteristics]
    corners: list[CornerCharacteristics]

    def to_json(self) -> dict[str, Any]:
        """Nested dict keyed by pose/path name, standard names and units in the keys."""
        return {
            "poses": {p.name: _clean(p.to_json()) for p in self.poses},
            "distances": {d.name: _clean(d.to_json()) for d in self.distances},
            "paths": {p.name: _clean(p.to_json()) for p in self.paths},
            "corners": {c.name: _clean(c.to_json()) for c in self.corners},
        }


def _clean(d: dict[str, Any]) -> dict[str, Any]:
    """Plain floats, NaN as None (valid JSON)."""
    out = {}
    for k, v in d.items():
        if isinstance(v, float | np.floating):
            out[k] = None if not np.isfinite(v) else float(v)
        else:
            out[k] = v
    return out


def iso9283(
    program: Program,
    time: Float[np.ndarray, " frames"],
    position: Float[np.ndarray, "frames 3"],
    quaternion_wxyz: Float[np.ndarray, "frames 4"],
    *,
    segment: np.ndarray | None = None,
    pose_names: dict[int, str] | None = None,
    speed_threshold: float = 0.005,
    min_dwell: float = 0.3,
    speed_window: float = 0.05,
    match_radius: float = 0.02,
    target_tolerance: float = 1e-4,
    band: float | None = None,
    drift_cycles: int | None = None,
    spacing: float | None = None,
    n_planes: int = 20,
    steady: tuple[float, float] = (0.25, 0.75),
    corner_angle: float = np.radians(30.0),
    n_boot: int = N_BOOT,
    seed: int = 0,
) -> Iso9283Result:
    """ISO 9283 pose, distance, path, corner and velocity characteristics.

    **Arguments:**

    - `program`: commanded targets in the base frame (at least two).
    - `time` `(N,)` [s], `position` `(N, 3)` [m], `quaternion_wxyz` `(N, 4)`: measured TCP
      poses in the base frame (NaN rows for unseen frames).
    - `segment` `(N,)`: program target approached per frame (`/program/segment`), optional;
      helps to assign dwells to targets.
    - `pose_names`: `{cluster id: name}` to rename test poses (ids in order of first
      appearance in the program, from 0).
    - `speed_threshold` [m/s], `min_dwell` [s], `speed_window` [s]: dwell detection from
      the measured speed (central differences over `speed_window`).
    - `match_radius` [m]: largest distance from a dwell to its target.
    - `target_tolerance` [m]: targets closer than this (and within 1 mrad) are one pose.
    - `band` [m]: limit band for stabilisation time and overshoot; default the pose's RP
      (at least 1 µm).
    - `drift_cycles`: cycles at the start and at the end compared for the drift;
      default a third of the cycles.
    - `spacing` [m]: reference sampling of the commanded path for the path tests; default
      half the mean measured step.
    - `n_planes`: normal planes per move for AT/RT; `steady`: fraction of each move used
      for the velocity characteristics; `corner_angle` [rad]: smallest change of
      direction that makes a corner.
    - `n_boot`, `seed`: bootstrap resamples and seed of the 95 % intervals (`_iso_ci`).

    **Returns:** an `Iso9283Result`. Raises `UserError` for a program with fewer than two
    targets or when no test pose is attained at least twice and no path move repeats.
    """
    time = np.asarray(time, np.float64)
    position = np.asarray(position, np.float64)
    quaternion_wxyz = np.asarray(quaternion_wxyz, np.float64)
    tp = np.asarray(program.targets.position, np.float64)
    tq = np.asarray(program.targets.quaternion_wxyz, np.float64)
    if tp.shape[0] < 2:
        raise UserError(f"ISO 9283 needs a program with at least two targets, got {tp.shape[0]}")
    if not (time.shape[0] == position.shape[0] == quaternion_wxyz.shape[0]):
        raise UserError("time, position and quaternion_wxyz must have the same number of frames")
    cluster = cluster_targets(tp, tq, target_tolerance, 1e-3)
    dwells = find_dwells(
        time,
        position,
        quaternion_wxyz,
        tp,
        segment,
        speed_threshold=speed_threshold,
        min_duration=min_dwell,
        speed_window=speed_window,
        match_radius=match_radius,
    )
    by_pose: dict[int, list[Dwell]] = {}
    for d in dwells:
        by_pose.setdefault(int(cluster[d.target]), []).append(d)
    test = sorted(c for c, ds in by_pose.items() if len(ds) >= 2)
    names = {c: f"P{i + 1}" for i, c in enumerate(test)}
    rest = [c for c in np.unique(cluster) if c not in names]
    names.update({int(c): f"T{i + 1}" for i, c in enumerate(rest)})
    if pose_names:
        names.update(pose_names)

    rng = np.random.default_rng(seed)
    poses = [
        _pose(names[c], c, by_pose[c], cluster, tp, tq, time, position, dwells, band,
              drift_cycles, rng, n_boot)
        for c in test
    ]  # fmt: skip
    distances = _distances(dwells, cluster, set(test), names, tp)
    paths, corners = path_characteristics(
        program, cluster, set(test), names, time, position, quaternion_wxyz,
        spacing=spacing, n_planes=n_planes, steady=steady, corner_angle=corner_angle,
        speed_window=speed_window, rng=rng, n_boot=n_boot,
    )  # fmt: skip
    if not poses and not paths:
        raise UserError(
            "no ISO 9283 cycles found: no program pose is attained (a dwell of "
            f"≥ {min_dwell} s below {speed_threshold * 1e3:g} mm/s within "
            f"{match_radius * 1e3:g} mm) at least twice, and no linear move repeats"
        )
    return Iso9283Result(poses, distances, paths, corners)


def _pose(
    name, c, ds, cluster, tp, tq, time, position, all_dwells, band, drift_cycles, rng, n_boot
):
    targets = np.array([d.target for d in ds])
    cp, cq = tp[targets[0]], tq[targets[0]]
    x = np.array([d.position for d in ds])
    q = np.array([d.quaternion_wxyz for d in ds])
    # multi-directional: group attainments by the pose they came from
    approach = np.array([cluster[t - 1] if t > 0 else -1 for t in targets])
    values, ci = pose_statistics(x, q, cp, cq, approach, drift_cycles, rng, n_boot)
    # stabilisation and overshoot: from the end of the previous dwell to the end of this one
    t_stab, ov = [], []
    lim = max(values["RP"], _MIN_BAND) if band is None else band
    stops = {d.start: prev_d.stop for prev_d, d in zip(all_dwells[:-1], all_dwells[1:])}
    for d in ds:
        lo = stops.get(d.start, max(0, d.start - (d.stop - d.start)))
        r = np.linalg.norm(position[lo : d.stop] - d.position, axis=1)
        # only the final approach: from the last frame farther than `_APPROACH_RADIUS`
        far = np.flatnonzero(r[: d.start - lo] > _APPROACH_RADIUS)
        if far.size:
            lo, r = lo + far[-1], r[far[-1] :]
        ok = np.isfinite(r)
        tt, r = time[lo : d.stop][ok], r[ok]
        inside = np.flatnonzero(r <= lim)
        if inside.size == 0:
            continue
        first = inside[0]
        outside = np.flatnonzero(r[first:] > lim)
        if outside.size == 0:
            t_stab.append(0.0)
        else:  # until the first frame after the last one outside the band
            settled = min(first + outside[-1] + 1, tt.size - 1)
            t_stab.append(float(tt[settled] - tt[first]))
        peak = float(r[first:].max())
        ov.append(peak if peak > lim else 0.0)

    def stat(v: list[float], f) -> float:
        return float(f(v)) if v else float("nan")

    # means of non-negative times and distances: Student t cut at 0 (`bounded`)
    ci["t_stab_mean"] = bounded(pair(*t_interval(np.array(t_stab))))
    ci["overshoot_mean"] = bounded(pair(*t_interval(np.array(ov))))
    return PoseCharacteristics(
        name=name,
        commanded_position=cp,
        commanded_quaternion_wxyz=cq,
        attained_position=x,
        attained_quaternion_wxyz=q,
        attained_time=np.array([time[(d.start + d.stop) // 2] for d in ds]),
        approach=approach,
        **values,
        t_stab_mean=stat(t_stab, np.mean),
        t_stab_max=stat(t_stab, np.max),
        overshoot_mean=stat(ov, np.mean),
        overshoot_max=stat(ov, np.max),
        ci=ci,
    )


def pose_statistics(
    x: Float[np.ndarray, "cycles 3"],
    q: Float[np.ndarray, "cycles 4"],
    commanded_position: Float[np.ndarray, "3"],
    commanded_quaternion_wxyz: Float[np.ndarray, "4"],
    approach: np.ndarray | None = None,
    drift_cycles: int | None = None,
    rng: np.random.Generator | None = None,
    n_boot: int = N_BOOT,
) -> tuple[dict[str, Any], dict[str, Interval]]:
    """Pose characteristics of one test pose from its attained poses, cycle by cycle.

    `x` [m] and `q` (w, x, y, z) in the base frame, in time order; `approach` `(cycles,)`
    labels the direction each attainment came from (vAP; default one direction).
    Returns the `PoseCharacteristics` fields (less the settling ones) and their 95 %
    intervals keyed by the JSON names without unit (``APx``, ``RP``, ``AP_angle``, …),
    in SI units.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    cp, cq = commanded_position, commanded_quaternion_wxyz
    n = x.shape[0]
    approach = np.zeros(n, np.int64) if approach is None else np.asarray(approach)
    ap_xyz, rp = _ap_rp(x, cp)
    abc = error_components(np.broadcast_to(cq, q.shape), q)
    q_mean = mean_quaternion(q)
    ang = rotation_angle(np.broadcast_to(q_mean, q.shape), q)
    ci: dict[str, Interval] = {}
    lo, hi = t_interval(x - cp)
    lo_abc, hi_abc = t_interval(abc)
    rlo, rhi = three_s_interval(abc)
    for k, axis in enumerate("xyz"):
        ci[f"AP{axis}"] = pair(lo[k], hi[k])
    for k, axis in enumerate("abc"):
        ci[f"AP{axis}"] = pair(lo_abc[k], hi_abc[k])
        ci[f"RP{axis}"] = pair(rlo[k], rhi[k])
    ci["AP"] = length_interval(x - cp, None, rng, n_boot)
    ci["RP"] = rp_gaussian_interval(x - x.mean(axis=0))
    # rotation vectors of the errors: the length of their mean is the single angle AP
    # to first order; lengths of the ones from the mean orientation are the angles of RP
    err = (to_rotation(q) * to_rotation(cq).inv()).as_rotvec()
    ci["AP_angle"] = length_interval(err, None, rng, n_boot)
    ci["RP_angle"] = rp_gaussian_interval((to_rotation(q) * to_rotation(q_mean).inv()).as_rotvec())

    labels = np.unique(approach)
    groups = [x[approach == g] for g in labels]
    if len(groups) > 1:
        bary = np.array([g.mean(axis=0) for g in groups])
        dist = np.linalg.norm(bary[:, None] - bary[None], axis=-1)
        i, j = np.unravel_index(np.argmax(dist), dist.shape)
        vap = float(dist[i, j])
        ci["vAP"] = length_interval(groups[i], groups[j], rng, n_boot)
    else:
        vap = float("nan")
        ci["vAP"] = NAN_INTERVAL
    if drift_cycles is None:
        drift_cycles = max(2, n // 3)
    if n >= 4 and 2 <= drift_cycles <= n // 2:
        early, late = x[:drift_cycles], x[-drift_cycles:]
        e_xyz, e_rp = _ap_rp(early, cp)
        l_xyz, l_rp = _ap_rp(late, cp)
        dap = abs(float(np.linalg.norm(l_xyz)) - float(np.linalg.norm(e_xyz)))
        drp = abs(l_rp - e_rp)

        # |AP| changes along the AP directions: project each group's cycles on its own
        # AP direction (lengths near-linear where |AP| ≫ its standard error)
        pe = (early - cp) @ (e_xyz / max(float(np.linalg.norm(e_xyz)), 1e-300))
        pl = (late - cp) @ (l_xyz / max(float(np.linalg.norm(l_xyz)), 1e-300))
        d, _, nu = welch(pe, pl)
        ci["dAP"] = abs_interval(d, *welch_interval(pe, pl), stats.t(nu))
        ci["dRP"] = abs_interval(*rp_difference(early, late))
    else:
        dap = drp = float("nan")
        ci["dAP"] = ci["dRP"] = NAN_INTERVAL
    values = {
        "n_cycles": n,
        "AP_xyz": ap_xyz,
        "AP": float(np.linalg.norm(ap_xyz)),
        "RP": rp,
        "AP_abc": abc.mean(axis=0),
        "RP_abc": 3.0 * np.std(abc, axis=0, ddof=1),
        "AP_angle": float(rotation_angle(cq, q_mean)),
        "RP_angle": float(ang.mean() + 3.0 * _s(ang)),
        "vAP": vap,
        "dAP": dap,
        "dRP": drp,
    }
    return values, ci


def _ap_rp(x: np.ndarray, commanded: np.ndarray) -> tuple[np.ndarray, float]:
    """ISO 9283 §7.2.1: AP vector (barycentre − command) and RP = l̄ + 3·S_l."""
    bary = x.mean(axis=0)
    l = np.linalg.norm(x - bary, axis=1)
    return bary - commanded, float(l.mean() + 3.0 * _s(l))


def _distances(dwells, cluster, test, names, tp) -> list[DistanceCharacteristics]:
    """ISO 9283 §7.4 between consecutively attained test poses (each ordered pair)."""
    pairs: dict[tuple[int, int], list[tuple[float, float]]] = {}
    for a, b in zip(dwells[:-1], dwells[1:]):
        ca, cb = int(cluster[a.target]), int(cluster[b.target])
        if ca in test and cb in test and ca != cb:
            dc = float(np.linalg.norm(tp[b.target] - tp[a.target]))
            pairs.setdefault((ca, cb), []).append(
                (float(np.linalg.norm(b.position - a.position)), dc)
            )
    out = []
    for (ca, cb), v in pairs.items():
        if len(v) < 2:
            continue
        d = np.array([x[0] for x in v])
        dc = v[0][1]
        # a distance is ≥ 0, so AD = D̄ − D_c ≥ −D_c
        ci = {"AD": bounded(pair(*t_interval(d - dc)), -dc), "RD": pair(*three_s_interval(d))}
        out.append(DistanceCharacteristics(f"{names[ca]}-{names[cb]}", dc, float(d.mean() - dc),
                                           3.0 * _s(d), len(v), ci))  # fmt: skip
    return out
