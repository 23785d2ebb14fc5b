"""`CalibrationResult`: the bundle calibration's output and its CALIB.json form (DESIGN §8),
and the result of a fit from what its steps found (`calibration_result`)."""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import numpy as np

from .._errors import UserError
from ..model import MOTION_THRESHOLD, Effects
from ..recording import Pose, Recording
from ._calib_data import recording_weights
from ._calib_residuals import Residuals
from ._calib_setup import Setup
from ._calib_solves import Solved
from ._calib_uncertainty import Uncertainty
from ._quoted_sigma import QuotedSigma, quoted_sigma, sigma_of

#: version of the CALIB.json schema written (DESIGN section 8); files without one are version 1
SCHEMA_VERSION = 2
#: versions this reader understands
READABLE_VERSIONS = (1, 2)
#: frames whose noise-normalised residual RMS exceeds this are outliers
OUTLIER_U = 4.0


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _float_or_nan(x) -> float:
    """A JSON number, or NaN for null (how NaN is written)."""
    return float("nan") if x is None else float(x)


@dataclasses.dataclass(frozen=True)
class CalibrationResult:
    """Result of `fit` (SI units; poses as `Pose`).

    Parameter vector of the covariance (`parameter_names`): ``camera_from_base.{tx..rz}``
    and ``flange_from_tool.{tx..rz}`` (tangent space at the estimate, right
    perturbation ``T̂ @ exp(δ)``), then each estimated effect entry (e.g.
    ``joint_offset[2]``, ``link_length[1].a``), then ``constellation[LED k].{x,y,z}``.
    Fixed (dropped or not estimated) parameters have zero variance; the covariance of
    parameters in a null direction of the data (``identifiability["undetermined"]``) is
    that of the minimum-norm solution and means nothing: `sigma` gives them inf.
    """

    camera_from_base: Pose
    flange_from_tool: Pose
    led_ids: np.ndarray
    constellation: np.ndarray
    effects: dict[str, Any]
    estimated: tuple[str, ...]
    parameter_names: tuple[str, ...]
    covariance: np.ndarray
    residual_rms_m: float
    noise_sigma_m: float
    gauge: str
    gauge_reference: np.ndarray
    identifiability: dict[str, Any]
    iterations: int
    converged: bool
    #: why the solver stopped (the first solve that did not converge, if any)
    convergence: str = ""
    chi2: float = float("nan")
    n_residuals: int = 0
    n_params: int = 0
    log_likelihood: float = float("nan")
    residual_rms_per_led: dict[int, float] = dataclasses.field(default_factory=dict)
    residual_rms_per_frame: np.ndarray | None = None
    # (N, leds, 3) measured − predicted [m] per frame and LED of `led_ids`, NaN unused
    residuals: np.ndarray | None = None
    # (N, recording LEDs) final weights [1/m²] in the recording's `led_ids` columns, 0 unused
    weights: np.ndarray | None = None
    outlier_frames: np.ndarray | None = None
    noise_model: dict[str, Any] = dataclasses.field(default_factory=dict)
    initial: dict[str, Pose] = dataclasses.field(default_factory=dict)
    unseen_leds: tuple[int, ...] = ()
    robust: str | None = None
    #: cluster-robust (delete-one-cluster jackknife) covariance over `n_clusters` clusters
    #: (`robtraj.estimate.robust_covariance`), same layout as `covariance`
    covariance_robust: np.ndarray | None = None
    n_clusters: int = 0
    #: per parameter, the clusters the robust σ effectively rests on
    #: (`robtraj.estimate.effective_clusters`; its relative error ≈ 1/√(2·G_eff))
    clusters_effective: np.ndarray | None = None
    #: covariance under the model-error field over the clusters' joint angles
    #: (`robtraj.estimate.field_covariance`), same layout as `covariance`; None where
    #: not estimated
    covariance_field: np.ndarray | None = None
    #: the field itself (`ModelErrorField.as_dict`: its lengths [rad], variance ratios,
    #: white share, deviance); empty where not estimated
    model_error: dict[str, Any] = dataclasses.field(default_factory=dict)
    #: speed [rad/s] below which a joint counted as at rest (the velocity-sign terms)
    motion_threshold: float = MOTION_THRESHOLD
    #: the robot model calibrated, as `RobotLog.model_document` (empty if not known)
    robot: dict[str, Any] = dataclasses.field(default_factory=dict)
    #: per joint angle error map in `effects` (``joint{j}_map``): ``{"knots_rad",
    #: "sigma_rad" (None where held at its prior mean), "estimated" (bool per knot),
    #: "fitted_range_rad" [lo, hi], "prior": {"sigma_f_rad", "length_scale_rad"}}``; the
    #: maps' σ live here, not in `covariance`
    maps: dict[str, Any] = dataclasses.field(default_factory=dict)
    #: how the model was made: ``{"command", "named" (effects in the order named),
    #: "naming", "recording"}`` (empty for a plain `calibrate`)
    provenance: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def time_offset(self) -> float:
        return float(np.asarray(self.effects.get("time_offset", 0.0)))

    @property
    def quoted(self) -> QuotedSigma:
        """The quoted σ in `parameter_names` order with the source that set each
        (`robtraj.estimate.quoted_sigma`): the largest of Gauss–Newton, the
        cluster-robust one (`covariance_robust`: does not shrink when the residual is
        not noise) and the one under the model-error field (`covariance_field`: also
        covers error shared by every cluster)."""

        def same_shape(c):
            return c if c is not None and np.shape(c) == np.shape(self.covariance) else None

        return quoted_sigma(
            sigma_of(self.covariance),
            sigma_of(same_shape(self.covariance_robust)),
            sigma_of(same_shape(self.covariance_field)),
        )

    @property
    def sigma(self) -> dict[str, float]:
        """Standard deviation per parameter name, the one to quote (`quoted`); inf for
        the parameters the recording does not determine
        (``identifiability["undetermined"]``)."""
        return self._named_sigma(self.quoted.sigma)

    @property
    def sigma_model(self) -> dict[str, float]:
        """Gauss–Newton standard deviation per parameter name (``s²H⁺``: right when the
        residual is noise of the assumed model), inf where undetermined."""
        return self._named_sigma(sigma_of(self.covariance))

    def _named_sigma(self, sigma: np.ndarray) -> dict[str, float]:
        out = dict(zip(self.parameter_names, np.asarray(sigma).tolist()))
        for name in (self.identifiability or {}).get("undetermined", []):
            if name in out:
                out[name] = float("inf")
        return out

    def effects_module(self, n_joints: int = 6) -> Effects:
        return Effects.from_dict(self.effects, n_joints)

    def to_json(self) -> dict[str, Any]:
        """The CALIB.json dictionary of DESIGN section 8."""

        def pose(p: Pose) -> dict:
            return {"position": p.position.tolist(), "quaternion_wxyz": p.quaternion_wxyz.tolist()}

        return {
            "schema_version": SCHEMA_VERSION,
            "camera_from_base": pose(self.camera_from_base),
            "flange_from_tool": pose(self.flange_from_tool),
            "constellation": {
                "led_ids": [int(i) for i in self.led_ids],
                "positions": np.asarray(self.constellation).tolist(),
            },
            "time_offset": self.time_offset,
            "motion_threshold_rad_s": self.motion_threshold,
            "covariance": {
                "parameters": list(self.parameter_names),
                "matrix": np.asarray(self.covariance).tolist(),
            },
            "covariance_robust": None
            if self.covariance_robust is None
            else {
                "matrix": np.asarray(self.covariance_robust).tolist(),
                "clusters": self.n_clusters,
                "effective_clusters": None
                if self.clusters_effective is None
                else [_finite_or_none(x) for x in np.asarray(self.clusters_effective)],
            },
            "covariance_field": None
            if self.covariance_field is None
            else {
                "matrix": np.asarray(self.covariance_field).tolist(),
                "model_error": self.model_error,
            },
            "residual_rms_m": self.residual_rms_m,
            "effects": {k: np.asarray(v).tolist() for k, v in self.effects.items()},
            "estimated": list(self.estimated),
            "gauge": {
                "kind": self.gauge,
                "reference_constellation": np.asarray(self.gauge_reference).tolist(),
            },
            "identifiability": self.identifiability,
            "noise_sigma_m": self.noise_sigma_m,
            "noise_model": self.noise_model,
            "chi2": self.chi2,
            "n_residuals": self.n_residuals,
            "n_params": self.n_params,
            "log_likelihood": self.log_likelihood,
            "iterations": self.iterations,
            "converged": self.converged,
            "convergence": self.convergence,
            "robust": self.robust,
            "residual_rms_per_led_m": {str(k): v for k, v in self.residual_rms_per_led.items()},
            "outlier_frames": []
            if self.outlier_frames is None
            else [int(i) for i in self.outlier_frames],
            "unseen_leds": list(self.unseen_leds),
            "robot": self.robot or None,
            "maps": self.maps,
            "provenance": self.provenance,
        }

    @classmethod
    def from_json(cls, d: dict[str, Any] | str) -> CalibrationResult:
        """Read back `to_json` output (a dict or a JSON string); per-frame arrays are absent."""
        if isinstance(d, str):
            d = json.loads(d)
        try:

            def pose(p):
                return Pose(
                    np.asarray(p["position"], float), np.asarray(p["quaternion_wxyz"], float)
                )

            cov = d.get("covariance", {})
            robust = d.get("covariance_robust") or {}
            field = d.get("covariance_field") or {}
            gauge = d.get("gauge", {})
            gauge = gauge if isinstance(gauge, dict) else {"kind": gauge}
            effects = dict(d.get("effects", {}))
            if "time_offset" in d and d["time_offset"]:
                effects.setdefault("time_offset", d["time_offset"])
            return cls(
                camera_from_base=pose(d["camera_from_base"]),
                flange_from_tool=pose(d["flange_from_tool"]),
                led_ids=np.asarray(d["constellation"]["led_ids"], np.int64),
                constellation=np.asarray(d["constellation"]["positions"], float).reshape(-1, 3),
                effects=effects,
                estimated=tuple(d.get("estimated", ())),
                parameter_names=tuple(cov.get("parameters", ())),
                covariance=np.asarray(cov.get("matrix", np.zeros((0, 0))), float),
                residual_rms_m=_float_or_nan(d.get("residual_rms_m")),
                noise_sigma_m=_float_or_nan(d.get("noise_sigma_m")),
                gauge=str(gauge.get("kind", "unknown")),
                gauge_reference=np.asarray(
                    gauge.get("reference_constellation", d["constellation"]["positions"]), float
                ).reshape(-1, 3),
                identifiability=d.get("identifiability", {}),
                iterations=int(d.get("iterations", 0)),
                converged=bool(d.get("converged", False)),
                convergence=str(d.get("convergence", "")),
                chi2=_float_or_nan(d.get("chi2")),
                n_residuals=int(d.get("n_residuals", 0)),
                n_params=int(d.get("n_params", 0)),
                log_likelihood=_float_or_nan(d.get("log_likelihood")),
                residual_rms_per_led={
                    int(k): float(v) for k, v in d.get("residual_rms_per_led_m", {}).items()
                },
                outlier_frames=np.asarray(d.get("outlier_frames", []), np.int64),
                noise_model=d.get("noise_model", {}),
                unseen_leds=tuple(d.get("unseen_leds", ())),
                robust=d.get("robust"),
                covariance_robust=(
                    np.asarray(robust["matrix"], float) if "matrix" in robust else None
                ),
                n_clusters=int(robust.get("clusters", 0)),
                covariance_field=(
                    np.asarray(field["matrix"], float) if "matrix" in field else None
                ),
                model_error=dict(field.get("model_error") or {}),
                motion_threshold=float(d.get("motion_threshold_rad_s", MOTION_THRESHOLD)),
                robot=dict(d.get("robot") or {}),
                maps=dict(d.get("maps") or {}),
                provenance=dict(d.get("provenance") or {}),
                clusters_effective=(
                    None
                    if robust.get("effective_clusters") is None
                    else np.array(
                        [np.nan if x is None else x for x in robust["effective_clusters"]], float
                    )
                ),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise UserError(f"not a robtraj calibration (CALIB.json): {e}") from None


def calibration_result(
    recording: Recording,
    st: Setup,
    solved: Solved,
    unc: Uncertainty,
    res: Residuals,
    robust: str | None,
) -> CalibrationResult:
    """The `CalibrationResult` of a fit of `recording`: its setup, its solves, the
    uncertainty and the residuals at the estimate; the covariances restricted to the
    parameters of the model (not the held effects)."""
    data, problem, q = st.data, solved.bundle.problem, st.q
    eff = problem.effects
    effects = {n: np.asarray(eff.get(n)).tolist() for n in st.free}
    effects.update({k: v for k, v in eff.to_dict().items() if k not in effects})
    model = np.flatnonzero(np.r_[st.in_model[:q], np.ones(len(unc.names) - q, bool)])
    with np.errstate(invalid="ignore", divide="ignore"):
        outliers = np.sqrt(res.frame_noise_square[data.frame] / unc.s2) > OUTLIER_U
    return CalibrationResult(
        robot=recording.robot.model_document(),
        camera_from_base=Pose.from_wxyz_xyz(problem.camera_from_base),
        flange_from_tool=Pose.from_wxyz_xyz(problem.flange_from_tool),
        led_ids=np.asarray(data.led_ids),
        constellation=np.asarray(problem.constellation),
        effects=effects,
        estimated=st.estimated,
        parameter_names=tuple(unc.names[i] for i in model),
        covariance=unc.covariance[np.ix_(model, model)],
        covariance_robust=unc.covariance_robust[np.ix_(model, model)],
        clusters_effective=unc.clusters_effective[model],
        n_clusters=unc.n_clusters,
        covariance_field=None
        if unc.covariance_field is None
        else unc.covariance_field[np.ix_(model, model)],
        model_error=unc.model_error,
        residual_rms_m=float(np.sqrt(res.mean_square)),
        noise_sigma_m=float(np.sqrt(res.mean_square / 3.0)),
        gauge=st.gauge,
        gauge_reference=np.asarray(data.reference),
        motion_threshold=data.motion_threshold,
        identifiability=unc.identifiability,
        iterations=solved.iterations,
        converged=solved.converged,
        convergence=solved.convergence,
        chi2=unc.chi2,
        n_residuals=unc.n_residuals,
        n_params=unc.rank,
        log_likelihood=unc.log_likelihood,
        residual_rms_per_led=res.rms_per_led,
        residual_rms_per_frame=res.rms_per_frame,
        residuals=res.residuals,
        weights=None if res.weights is None else recording_weights(data, res.weights),
        outlier_frames=data.frame[outliers],
        noise_model=st.noise_info,
        initial=st.initial,
        unseen_leds=data.unseen_leds,
        robust=robust,
    )
