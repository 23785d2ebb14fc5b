"""ISO 9283 path characteristics: AT/RT (§8.2–8.3), corners CR/CO (§8.5), AV/RV/FV (§8.6)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..recording import Program
from ._dwell import smoothed_speed
from ._quat import error_components, mean_quaternion, rotation_angle, slerp
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
    (max − min speed) [m/s]. `plane_AT`, `plane_RT` `(n_planes,)` per plane.
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

    def to_json(self) -> dict[str, Any]:
        mm, deg = 1e3, float(np.degrees(1.0))
        return {
            "n_cycles": self.n_cycles,
            "length_mm": self.length * mm,
            "vc_mm_per_s": self.commanded_speed * mm,
            "AT_mm": self.AT * mm,
            "RT_mm": self.RT * mm,
            "ATa_deg": self.AT_abc[0] * deg,
            "ATb_deg": self.AT_abc[1] * deg,
            "ATc_deg": self.AT_abc[2] * deg,
            "AT_angle_deg": self.AT_angle * deg,
            "RTa_deg": self.RT_abc[0] * deg,
            "RTb_deg": self.RT_abc[1] * deg,
            "RTc_deg": self.RT_abc[2] * deg,
            "v_mean_mm_per_s": self.mean_speed * mm,
            "AV_percent": self.AV * 100,
            "RV_percent": self.RV * 100,
            "FV_mm_per_s": self.FV * mm,
        }


@dataclasses.dataclass(frozen=True)
class CornerCharacteristics:
    """Corner round-off `CR` (closest approach of the measured path to the corner) and
    corner overshoot `CO` (largest deviation from the second leg in its first half) [m],
    mean and max over `n` passes."""

    name: str
    n: int
    CR_mean: float
    CR_max: float
    CO_mean: float
    CO_max: float

    def to_json(self) -> dict[str, Any]:
        return {"n": self.n, "CR_mean_mm": self.CR_mean * 1e3, "CR_max_mm": self.CR_max * 1e3,
                "CO_mean_mm": self.CO_mean * 1e3, "CO_max_mm": self.CO_max * 1e3}  # fmt: skip


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
        valid = np.all(np.isfinite(x), axis=2)  # (occ, planes)
        use = valid.sum(axis=0) >= 2
        bary = np.full((n_planes, 3), np.nan)
        at = np.full(n_planes, np.nan)
        rt = np.full(n_planes, np.nan)
        at_abc = np.full((n_planes, 3), np.nan)
        rt_abc = np.full((n_planes, 3), np.nan)
        at_ang = np.full(n_planes, np.nan)
        for i in np.flatnonzero(use):  # per plane (tens), vectorised over passes
            xi, qi = x[valid[:, i], i], q[valid[:, i], i]
            bary[i] = xi.mean(axis=0)
            at[i] = np.linalg.norm(bary[i] - c[i])
            l = np.linalg.norm(xi - bary[i], axis=1)
            rt[i] = l.mean() + 3.0 * np.std(l, ddof=1)
            e = error_components(np.broadcast_to(qc[i], qi.shape), qi)
            at_abc[i] = np.abs(e.mean(axis=0))
            rt_abc[i] = 3.0 * np.std(e, axis=0, ddof=1)
            at_ang[i] = rotation_angle(qc[i], mean_quaternion(qi))
        vc = float(program.speed[j0])
        vm = np.array(v_mean)
        paths.append(
            PathCharacteristics(
                name=f"{names[a]}->{names[b]}",
                n_cycles=int(valid.any(axis=1).sum()),
                length=float(length[j0]),
                commanded_speed=vc,
                AT=_nanmax(at),
                RT=_nanmax(rt),
                AT_abc=_nanmax(at_abc, axis=0),
                RT_abc=_nanmax(rt_abc, axis=0),
                AT_angle=_nanmax(at_ang),
                mean_speed=float(vm.mean()) if vm.size else float("nan"),
                AV=float((vm.mean() - vc) / vc) if vm.size and vc > 0 else float("nan"),
                RV=float(3.0 * np.std(vm, ddof=1) / vc) if vm.size > 1 and vc > 0 else float("nan"),
                FV=float(max(v_fluct)) if v_fluct else float("nan"),
                plane_fraction=planes,
                plane_AT=at,
                plane_RT=rt,
            )
        )
    return paths, _corners(moves, cluster, names, tp, position, dev, frac_all, corner_angle)


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
    out = []
    for c, v in found.items():
        if len(v) < 1:
            continue
        cr, co = np.array(v).T
        out.append(CornerCharacteristics(names[c], len(v), float(cr.mean()), float(cr.max()),
                                         float(co.mean()), float(co.max())))  # fmt: skip
    return out
