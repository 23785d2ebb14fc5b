"""ISO 9283 path characteristics: AT/RT (§8.2–8.3), corners CR/CO (§8.5), AV/RV/FV (§8.6)."""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any

import numpy as np
from jaxtyping import Float

from ..recording import Program
from ._dwell import smoothed_speed
from ._iso_ci import (
    N_BOOT,
    Interval,
    batch_rotation_angle,
    bounded,
    max_length_interval,
    max_scale_interval,
    pair,
    rp_scale,
    t_interval,
    three_s_interval,
    with_intervals,
)
from ._quat import error_components, slerp, to_rotation
from .deviation import commanded_path, path_deviation

_MAX_REFERENCE_SAMPLES = 2_000_000


@dataclasses.dataclass(frozen=True)
class PathCharacteristics:
    """Path accuracy/repeatability and velocity characteristics of one repeated linear move.

    Over `n_cycles` passes and `n_planes` planes normal to the commanded line:
    `AT` = max over planes of |barycentre − command| [m], `RT` = max over planes of
    l̄ + 3·S_l [m]; `AT_abc`, `RT_abc` the same per orientation component [rad] (max of
    |mean error| and of 3·S), `AT_angle` the largest single angle between the mean
    attained and the commanded orientation [rad]. Velocity over the `steady` part of the
    move: `AV` = (v̄ − v_c)/v_c, `RV` = 3·S_v̄/v_c (fractions), `FV` = max over passes of
    (max − min speed) [m/s]. `plane_AT`, `plane_RT` `(n_planes,)` per plane. `ci`: 95 %
    intervals keyed by the JSON names without unit, in SI (fractions for AV, RV):
    the restricted parametric bootstrap of the maximum over planes for AT (studentised;
    position, a/b/c, angle; `max_length_interval`) and for RT (position, a/b/c;
    `max_scale_interval`), Student t / χ² for AV / RV; none for FV (a maximum over
    passes).
    """

    name: str
    n_cycles: int
    length: float
    commanded_speed: float
    AT: float
    RT: float
    AT_abc: np.ndarray
    RT_abc: np.ndarray
    AT_angle: float
    mean_speed: float
    AV: float
    RV: float
    FV: float
    plane_fraction: np.ndarray
    plane_AT: np.ndarray
    plane_RT: np.ndarray
    ci: dict[str, Interval] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        mm, deg = 1e3, float(np.degrees(1.0))
        rows = [
            ("AT_mm", self.AT, mm), ("RT_mm", self.RT, mm),
            ("ATa_deg", self.AT_abc[0], deg), ("ATb_deg", self.AT_abc[1], deg),
            ("ATc_deg", self.AT_abc[2], deg), ("AT_angle_deg", self.AT_angle, deg),
            ("RTa_deg", self.RT_abc[0], deg), ("RTb_deg", self.RT_abc[1], deg),
            ("RTc_deg", self.RT_abc[2], deg), ("v_mean_mm_per_s", self.mean_speed, mm),
            ("AV_percent", self.AV, 100.0), ("RV_percent", self.RV, 100.0),
            ("FV_mm_per_s", self.FV, mm),
        ]  # fmt: skip
        head = {
            "n_cycles": self.n_cycles,
            "length_mm": self.length * mm,
            "vc_mm_per_s": self.commanded_speed * mm,
        }
        return head | with_intervals(rows, self.ci, {})


@dataclasses.dataclass(frozen=True)
class CornerCharacteristics:
    """Corner round-off `CR` (closest approach of the measured path to the commanded
    corner `commanded_position`) and corner overshoot `CO` (largest distance from the
    commanded path of the frames nearest to the second leg, in its first half) [m],
    mean and max over `n` passes; `ci`: Student-t 95 % intervals of the means."""

    name: str
    commanded_position: np.ndarray
    n: int
    CR_mean: float
    CR_max: float
    CO_mean: float
    CO_max: float
    ci: dict[str, Interval] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        rows = [("CR_mean_mm", self.CR_mean, 1e3), ("CR_max_mm", self.CR_max, 1e3),
                ("CO_mean_mm", self.CO_mean, 1e3), ("CO_max_mm", self.CO_max, 1e3)]  # fmt: skip
        head = {"n": self.n, "commanded_mm": (self.commanded_position * 1e3).tolist()}
        return head | with_intervals(rows, self.ci, {})


def path_characteristics(
    program: Program,
    cluster: np.ndarray,
    test: set[int],
    names: dict[int, str],
    time: np.ndarray,
    position: np.ndarray,
    quaternion_wxyz: np.ndarray,
    *,
    spacing: float | None,
    n_planes: int,
    steady: tuple[float, float],
    corner_angle: float,
    speed_window: float,
    rng: np.random.Generator,
    n_boot: int = N_BOOT,
) -> tuple[list[PathCharacteristics], list[CornerCharacteristics]]:
    tp = np.asarray(program.targets.position, np.float64)
    tq = np.asarray(program.targets.quaternion_wxyz, np.float64)
    motion = np.asarray(program.motion).astype(str)
    length = np.concatenate([[0.0], np.linalg.norm(np.diff(tp, axis=0), axis=1)])
    s_start = np.concatenate([[0.0], np.cumsum(length[1:])]) - length  # progress at move start
    moves: dict[tuple[int, int], list[int]] = {}
    for j in range(1, tp.shape[0]):
        a, b = int(cluster[j - 1]), int(cluster[j])
        if motion[j] == "linear" and length[j] > 1e-9 and not (a in test and b in test):
            moves.setdefault((a, b), []).append(j)
    moves = {k: v for k, v in moves.items() if len(v) >= 2}
    if not moves:
        return [], []

    if spacing is None:
        step = np.nanmean(np.linalg.norm(np.diff(position, axis=0), axis=1))
        spacing = float(np.clip(0.5 * step, 1e-5, 5e-3)) if np.isfinite(step) else 1e-3
    spacing = max(spacing, float(length.sum()) / _MAX_REFERENCE_SAMPLES)
    dev = path_deviation(commanded_path(program, spacing), position, quaternion_wxyz)
    speed = smoothed_speed(time, position, speed_window)
    frac_all = np.full(time.shape[0], np.nan)
    ok = dev.target >= 1
    frac_all[ok] = (dev.progress[ok] - s_start[dev.target[ok]]) / np.maximum(
        length[dev.target[ok]], 1e-12
    )
    planes = (np.arange(n_planes) + 0.5) / n_planes

    paths = []
    for (a, b), occ in moves.items():
        x = np.full((len(occ), n_planes, 3), np.nan)
        q = np.full((len(occ), n_planes, 4), np.nan)
        v_mean, v_fluct = [], []
        for o, j in enumerate(occ):
            m = np.flatnonzero((dev.target == j) & np.isfinite(dev.distance))
            if m.size < 2:
                continue
            f = np.maximum.accumulate(frac_all[m])
            fu, first = np.unique(f, return_index=True)
            mm = m[first]
            inside = (planes >= fu[0]) & (planes <= fu[-1])
            for k in range(3):
                x[o, inside, k] = np.interp(planes[inside], fu, position[mm, k])
            hi = np.clip(np.searchsorted(fu, planes[inside]), 1, fu.size - 1)
            w = (planes[inside] - fu[hi - 1]) / np.maximum(fu[hi] - fu[hi - 1], 1e-15)
            q[o, inside] = slerp(quaternion_wxyz[mm[hi - 1]], quaternion_wxyz[mm[hi]], w)
            sel = m[(frac_all[m] >= steady[0]) & (frac_all[m] <= steady[1])]
            v = speed[sel][np.isfinite(speed[sel])]
            if v.size:
                v_mean.append(float(v.mean()))
                v_fluct.append(float(v.max() - v.min()))
        j0 = occ[0]
        c = tp[j0 - 1] + planes[:, None] * (tp[j0] - tp[j0 - 1])
        qc = slerp(
            np.broadcast_to(tq[j0 - 1], (n_planes, 4)),
            np.broadcast_to(tq[j0], (n_planes, 4)),
            planes,
        )
        vc = float(program.speed[j0])
        values, ci = path_statistics(x, q, c, qc, np.array(v_mean), vc, rng, n_boot)
        paths.append(
            PathCharacteristics(
                name=f"{names[a]}->{names[b]}",
                length=float(length[j0]),
                commanded_speed=vc,
                FV=float(max(v_fluct)) if v_fluct else float("nan"),
                plane_fraction=planes,
                ci=ci,
                **values,
            )
        )
    return paths, _corners(moves, cluster, names, tp, position, dev, frac_all, corner_angle)


def path_statistics(
    x: Float[np.ndarray, "passes planes 3"],
    q: Float[np.ndarray, "passes planes 4"],
    commanded: Float[np.ndarray, "planes 3"],
    commanded_quaternion_wxyz: Float[np.ndarray, "planes 4"],
    v_mean: Float[np.ndarray, " timed_passes"],
    commanded_speed: float,
    rng: np.random.Generator | None = None,
    n_boot: int = N_BOOT,
) -> tuple[dict[str, Any], dict[str, Interval]]:
    """AT/RT (position, a/b/c, single angle) and AV/RV of one path from the attained
    poses where each pass crosses the normal planes (NaN where a pass misses a plane;
    planes crossed by fewer than two passes are left out) and the mean steady speed of
    each pass that has steady frames [m/s]. Returns the `PathCharacteristics` fields and
    their 95 % intervals.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    valid = np.all(np.isfinite(x), axis=2)  # (passes, planes)
    use = valid.sum(axis=0) >= 2
    x, q, c, qc = x[:, use], q[:, use], commanded[use], commanded_quaternion_wxyz[use]
    e = np.full(x.shape, np.nan)
    ok = np.all(np.isfinite(q), axis=-1)
    e[ok] = error_components(np.broadcast_to(qc, q.shape)[ok], q[ok])
    q0 = np.where(ok[..., None], q, 0.0)  # missing passes add nothing to the quaternion sum

    def plane_at(xb):
        return np.linalg.norm(np.nanmean(xb, axis=-3) - c, axis=-1)

    def plane_rt(xb):
        l = np.linalg.norm(xb - np.nanmean(xb, axis=-3, keepdims=True), axis=-1)
        return np.nanmean(l, axis=-2) + 3.0 * np.nanstd(l, axis=-2, ddof=1)

    def plane_angle(qb):
        s = np.where(np.sum(qb * qc, axis=-1, keepdims=True) < 0, -qb, qb).sum(axis=-3)
        return batch_rotation_angle(qc, s / np.linalg.norm(s, axis=-1, keepdims=True))

    at_all = np.full(use.size, np.nan)
    rt_all = np.full(use.size, np.nan)
    ci: dict[str, Interval] = {}
    at_abc = rt_abc = np.full(3, np.nan)
    at_angle = float("nan")
    if use.any():  # otherwise no plane is crossed by two passes
        with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)  # a resample can miss a plane
            at_all[use], rt_all[use] = plane_at(x), plane_rt(x)
            at_abc = np.nanmax(np.abs(np.nanmean(e, axis=0)), axis=0)
            s3 = 3.0 * np.nanstd(e, axis=0, ddof=1)  # (planes, 3)
            rt_abc = np.nanmax(s3, axis=0)
            at_angle = float(np.nanmax(plane_angle(q0)))
            ci["AT"] = max_length_interval(x - c, rng, n_boot)
            # RT: the restricted parametric bootstrap of a maximum (`max_scale_interval`)
            ok_p = np.all(np.isfinite(x), axis=-1)
            rt_dof = np.array([
                rp_scale(x[ok_p[:, i], i] - x[ok_p[:, i], i].mean(0))
                for i in range(x.shape[1])
            ])  # fmt: skip
            ci["RT"] = max_scale_interval(rt_dof[:, 0], rt_dof[:, 1], rng, n_boot)
            n_e = np.sum(np.isfinite(e), axis=0)
            for k, axis in enumerate("abc"):
                ek = e[..., k]
                ci[f"AT{axis}"] = max_length_interval(ek[..., None], rng, n_boot)
                ci[f"RT{axis}"] = max_scale_interval(s3[:, k], n_e[:, k] - 1.0, rng, n_boot)
            # rotation vectors of the errors: the length of their mean is the single
            # angle of the mean orientation to first order
            rv = np.full(x.shape, np.nan)
            rv[ok] = (
                to_rotation(q[ok]) * to_rotation(np.broadcast_to(qc, q.shape)[ok]).inv()
            ).as_rotvec()
            ci["AT_angle"] = max_length_interval(rv, rng, n_boot)
    vm, vc = np.asarray(v_mean, np.float64), commanded_speed
    has_v = vm.size > 0 and vc > 0
    if has_v:
        # a speed is ≥ 0: v̄ ≥ 0 and AV = (v̄ − v_c)/v_c ≥ −1
        ci["v_mean"] = bounded(pair(*t_interval(vm)))
        ci["AV"] = bounded(pair(*t_interval(vm / vc - 1.0)), -1.0)
        ci["RV"] = pair(*three_s_interval(vm / vc))
    values = {
        "n_cycles": int(valid.any(axis=1).sum()),
        "AT": _nanmax(at_all),
        "RT": _nanmax(rt_all),
        "AT_abc": at_abc,
        "RT_abc": rt_abc,
        "AT_angle": at_angle,
        "mean_speed": float(vm.mean()) if vm.size else float("nan"),
        "AV": float((vm.mean() - vc) / vc) if has_v else float("nan"),
        "RV": float(3.0 * np.std(vm, ddof=1) / vc) if has_v and vm.size > 1 else float("nan"),
        "plane_AT": at_all,
        "plane_RT": rt_all,
    }
    return values, ci


def _nanmax(v: np.ndarray, axis: int | None = None) -> Any:
    v = np.asarray(v)
    if axis is None:
        return float(np.max(v[np.isfinite(v)])) if np.any(np.isfinite(v)) else float("nan")
    out = np.full(v.shape[1 - axis], np.nan)
    fin = np.isfinite(v)
    for k in range(out.size):
        col = v[:, k][fin[:, k]]
        if col.size:
            out[k] = col.max()
    return out


def _corners(moves, cluster, names, tp, position, dev, frac_all, corner_angle):
    path_moves = {j for occ in moves.values() for j in occ}
    found: dict[int, list[tuple[float, float]]] = {}
    point: dict[int, np.ndarray] = {}
    for j in sorted(path_moves):
        if j + 1 not in path_moves:
            continue
        d1, d2 = tp[j] - tp[j - 1], tp[j + 1] - tp[j]
        cos = np.dot(d1, d2) / (np.linalg.norm(d1) * np.linalg.norm(d2))
        if np.arccos(np.clip(cos, -1.0, 1.0)) < corner_angle:
            continue
        near = np.flatnonzero(
            ((dev.target == j) | (dev.target == j + 1)) & np.isfinite(dev.distance)
        )
        leg2 = np.flatnonzero((dev.target == j + 1) & (frac_all < 0.5) & np.isfinite(dev.distance))
        if near.size == 0 or leg2.size == 0:
            continue
        cr = float(np.min(np.linalg.norm(position[near] - tp[j], axis=1)))
        co = float(np.max(dev.distance[leg2]))
        found.setdefault(int(cluster[j]), []).append((cr, co))
        point.setdefault(int(cluster[j]), tp[j])
    out = []
    for c, v in found.items():
        if len(v) < 1:
            continue
        cr, co = np.array(v).T
        # distances: Student t cut at 0 (`bounded`)
        ci = {"CR_mean": bounded(pair(*t_interval(cr))), "CO_mean": bounded(pair(*t_interval(co)))}
        out.append(CornerCharacteristics(names[c], point[c], len(v), float(cr.mean()),
                                         float(cr.max()), float(co.mean()), float(co.max()),
                                         ci))  # fmt: skip
    return out
