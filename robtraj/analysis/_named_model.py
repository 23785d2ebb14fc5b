"""A pose-level fit as a calibration (CALIB.json): the named model every command reads.

The pose fit (`_pose_fit.fit_poses`) and the bundle calibration share the forward model
(`robtraj.model`: effects, dictionary terms, the joint angle error maps), so a `PoseFit`
is written in the `CalibrationResult` layout: its rigid transforms, the effects it
estimated (maps as their dictionary terms ``joint{j}_map``), the Gauss–Newton covariance
of the parameters before the maps and, as the robust covariance, the σ it quotes (the
largest of Gauss–Newton, region jackknife and model-error field, `PoseFit.sigma`,
diagonal), the maps' knots with their posterior σ and the joint range fitted. The tool
is the recording's virtual points: a 6-DOF probe pose is exact on them.

The one convention that differs: the pose fit's drift variable is the temperature
about the series mean, the recording's about its first frame; camera←base is moved to
the first frame's temperature so that both predict the same poses.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import jaxlie
import numpy as np

from ..estimate import POSE_EFFECTS, pose_effects, pose_theta
from ..estimate.calibration import CalibrationResult
from ..model import (
    MAP_KNOTS,
    camera_from_base_at,
    effect_component_names,
    map_active,
    map_knots,
    pose_se3,
)
from ..recording import Pose, Recording
from ._pose_fit import (
    HARMONIC_TERMS,
    MAP_TERMS,
    N_PARAMS,
    PoseFit,
    fit_poses,
    frozen_fit,
    parameter_names,
    parse_effect_spec,
)
from ._pose_series import PoseSeries, series_from_recording


def pose_calibration(
    fit: PoseFit,
    rec: Recording,
    series: PoseSeries,
    *,
    named: Sequence[str],
    noise_m: float,
    source: str,
) -> CalibrationResult:
    """`fit` (of `series`, read from `rec`) as a `CalibrationResult` holding the effects
    `named` (pose-fit effect specs, e.g. ``joint_compliance[1,2]``, ``joint_map``), with
    `noise_m` the tracker's per-axis position noise [m] (0: not reported) and `source`
    the recording's path (provenance)."""
    entries = _calibrated_entries(fit)
    names = [parameter_names()[i] for i in entries]
    sigma = np.asarray(fit.sigma)[entries]
    return CalibrationResult(
        camera_from_base=_camera_at_first_frame(fit, series),
        flange_from_tool=Pose.from_wxyz_xyz(fit.flange_from_probe),
        led_ids=np.asarray(rec.tool.led_ids),
        constellation=np.asarray(rec.tool.constellation, float),
        effects=_effect_values(fit, named),
        estimated=_estimated_effects(fit, named),
        parameter_names=tuple(names),
        covariance=np.asarray(fit.covariance)[np.ix_(entries, entries)],
        covariance_robust=np.diag(np.nan_to_num(sigma) ** 2),
        residual_rms_m=float(np.sqrt(np.mean(fit.position_error**2) / 3.0)),
        noise_sigma_m=float(noise_m) if noise_m > 0 else float("nan"),
        gauge="tool (virtual points of the probe)",
        gauge_reference=np.asarray(rec.tool.constellation, float),
        identifiability={
            "dropped": fit.identifiability["dropped"],
            "undetermined": list(fit.identifiability.get("undetermined", [])),
        },
        iterations=fit.iterations,
        converged=fit.converged,
        chi2=fit.chi2,
        n_residuals=fit.n_residuals,
        n_params=int(round(fit.effective_parameters)),
        noise_model={
            "kind": "pose blocks",
            "position_sigma_m": fit.block_sigma[0],
            "rotation_sigma_rad": fit.block_sigma[1],
            "tracker_noise_m": noise_m,
        },
        robot=rec.robot.model_document() if rec.robot is not None else {},
        maps=_map_documents(fit, series),
        provenance={
            "command": "discrepancy",
            "recording": str(source),
            "named": list(named),
            "naming": "blocked cross-validation inside the recording",
        },
    )


def _calibrated_entries(fit: PoseFit) -> np.ndarray:
    """θ entries before the maps that the fit estimated (rigid transforms included)."""
    return np.flatnonzero(np.asarray(fit.free[:N_PARAMS]))


def _camera_at_first_frame(fit: PoseFit, series: PoseSeries):
    """camera←base at the first pose's drift variable (the recording's convention)."""
    eff = pose_effects(jnp.asarray(fit.theta))
    first = jnp.asarray(series.drift_variable[:1])
    z = camera_from_base_at(jaxlie.SE3(jnp.asarray(fit.camera_from_base)), eff, first)
    return Pose.from_wxyz_xyz(np.asarray(z.wxyz_xyz)[0])


def _effect_values(fit: PoseFit, named: Sequence[str]) -> dict[str, Any]:
    """The named effects' values by effect name (a per-joint subset such as
    ``joint_compliance[1,2]`` is the whole field, zero on the joints not estimated)."""
    values = pose_effects(jnp.asarray(fit.theta))
    out: dict[str, Any] = {}
    for name in _estimated_effects(fit, named):
        out[name] = np.asarray(values.get(name)).tolist()
    return out


def _estimated_effects(fit: PoseFit, named: Sequence[str]) -> tuple[str, ...]:
    """Effect names (library fields, dictionary terms) of the `named` pose-fit specs; a
    map only where the fit estimated any of its knots."""
    fitted = [MAP_TERMS[j - 1] for j in sorted(fit.maps())]
    out: list[str] = []
    for spec in named:
        block, _ = parse_effect_spec(spec)
        if block == "joint_map":
            out += [t for t in fitted if t in _map_terms(spec)]
        elif block == "joint_harmonic":
            out.append(spec)
        else:
            out.append(spec.partition("[")[0])
    return tuple(dict.fromkeys(out))


def _map_terms(spec: str) -> tuple[str, ...]:
    return MAP_TERMS if spec == "joint_map" else (spec,)


def _map_documents(fit: PoseFit, series: PoseSeries) -> dict[str, Any]:
    """Per estimated map: the knots, their posterior σ (None where held at zero),
    which knots were estimated, the joint range of the fitted poses and the prior."""
    out = {}
    prior = fit.map_prior
    for j, m in fit.maps().items():
        q = np.asarray(series.joints[:, j - 1], float)
        out[MAP_TERMS[j - 1]] = {
            "knots_rad": map_knots(MAP_KNOTS).tolist(),
            "sigma_rad": [None if not np.isfinite(s) else float(s) for s in m["sigma"]],
            "estimated": [bool(e) for e in m["estimated"]],
            "fitted_range_rad": [float(q.min()), float(q.max())],
            "prior": None
            if prior is None
            else {"sigma_f_rad": float(prior[0]), "length_scale_rad": float(prior[1])},
        }
    return out


# ----------------------------------------------------------------------------- back


def pose_representable(calib: CalibrationResult) -> bool:
    """Whether every non-zero effect of `calib` is one the pose fit carries (the
    library's static-pose effects, the joint harmonics, the maps)."""
    for name, value in calib.effects.items():
        if name in POSE_EFFECTS or name in HARMONIC_TERMS or name in MAP_TERMS:
            continue
        if np.any(np.asarray(value) != 0):
            return False
    return True


def pose_model(calib: CalibrationResult, series: PoseSeries) -> PoseFit:
    """`calib` as a frozen pose-fit model of `series`' convention: its effects in the
    θ layout (with the map block where it has maps), camera←base at the series' mean
    drift variable, flange←probe its flange←tool."""
    maps = any(t in calib.effects for t in MAP_TERMS)
    theta = pose_theta(calib.effects_module(), maps)
    eff = pose_effects(jnp.asarray(theta))
    z = pose_se3(calib.camera_from_base)
    first = jnp.asarray(-series.drift_variable[:1])
    z0 = np.asarray(camera_from_base_at(z, eff, first).wxyz_xyz)[0]
    x0 = np.asarray(pose_se3(calib.flange_from_tool).wxyz_xyz)
    return frozen_fit(theta, z0, x0, tuple(calib.estimated))


def pose_prediction(
    rec: Recording, calib: CalibrationResult, refit: Sequence[str]
) -> tuple[PoseFit, CalibrationResult]:
    """The 6-DOF prediction of the probe poses of `rec` by `calib` with its effects
    frozen and the rigid transforms `refit` (``camera_from_base``, ``flange_from_tool``)
    refitted by the pose residual, weighted as the discrepancy workflow weights a
    cross-series prediction (block σ of the nominal rigid fit); returns the prediction
    and `calib` with the refitted transforms."""
    series = series_from_recording(rec, "evaluated")
    model = pose_model(calib, series)
    rigid = tuple(
        r
        for r, full in (("camera", "camera_from_base"), ("probe", "flange_from_tool"))
        if full in refit
    )
    nominal = fit_poses(series, rigid=("camera", "probe"), maps_layout=model.has_maps)
    pred = fit_poses(series, fixed=model, rigid=rigid, block_sigma=nominal.block_sigma)
    refitted = dataclasses.replace(
        calib,
        camera_from_base=_camera_at_first_frame(pred, series),
        flange_from_tool=Pose.from_wxyz_xyz(pred.flange_from_probe),
        converged=pred.converged,
        iterations=pred.iterations,
    )
    return pred, refitted


# ----------------------------------------------------------------------------- LED path


def named_calibration(result, rec: Recording, source: str) -> CalibrationResult:
    """The final model of a discrepancy run on the LED recording `rec` (read from
    `source`; `discover`'s `DiscrepancyResult`) as a calibration: its calibration with
    the provenance of the naming and, for any map it named, the map's knots and σ."""
    calib = result.calibration
    return dataclasses.replace(
        calib,
        maps=_estimated_maps(calib, None if rec.robot is None else rec.robot.joints),
        provenance={
            "command": "discrepancy",
            "recording": str(source),
            "named": list(result.named),
            "naming": "score test screen; likelihood ratio, BIC and held-out time blocks",
        },
    )


def _estimated_maps(calib: CalibrationResult, joints: np.ndarray | None) -> dict[str, Any]:
    """`_map_documents` for a bundle calibration: a knot is estimated where it has a σ."""
    sigma = calib.sigma
    out = {}
    for j, t in enumerate(MAP_TERMS):
        if t not in calib.effects:
            continue
        names = effect_component_names(t, (MAP_KNOTS,))
        s = np.array([sigma.get(n, np.nan) for n in names], float)
        ok = np.isfinite(s) & (s > 0)
        q = None if joints is None else np.asarray(joints[:, j], float)
        out[t] = {
            "knots_rad": map_knots(MAP_KNOTS).tolist(),
            "sigma_rad": [float(v) if k else None for v, k in zip(s, ok)],
            "estimated": ok.tolist(),
            "fitted_range_rad": None if q is None else [float(q.min()), float(q.max())],
            "prior": None,
        }
    return out


def outside_maps(calib: CalibrationResult, joints: np.ndarray) -> list[dict[str, Any]]:
    """Per joint angle error map of `calib`, the share of the rows of `joints` `(N,
    joints)` [rad] at angles where the map was not fitted (either knot around the angle
    held at its prior mean, zero): ``[{"joint" (1-based), "map", "fraction",
    "fitted_range_rad"}]``, only maps with such rows."""
    out = []
    q = np.asarray(joints, float)
    for name, doc in sorted(calib.maps.items()):
        j = MAP_TERMS.index(name)
        if q.size == 0 or j >= q.shape[1]:
            continue
        estimated = np.asarray(doc["estimated"], bool)
        idx, _ = map_active(q[:, j], estimated.size)
        off = ~estimated[idx].all(-1)
        if off.any():
            out.append(
                {
                    "joint": j + 1,
                    "map": name,
                    "fraction": float(off.mean()),
                    "fitted_range_rad": doc.get("fitted_range_rad"),
                }
            )
    return out
