"""Estimation: static segments, LED registration, weighting schemes, per-frame poses, and
the one least-squares engine (`solve`, `identifiability`, `covariance`,
`robust_covariance`; Gaussian priors on terms, `GaussianPrior`; the σ a fit quotes,
`quoted_sigma`).

Bundle calibration lives in `robtraj.estimate.calibration`.
"""

from ._base_frame import base_frame_poses
from ._chunks import visible_frames
from ._clock import (
    ClockAlignment,
    align_clocks,
    clock_effects,
    robot_speeds,
    stream_speeds,
    tool_poses,
    tracker_speeds,
)
from ._model_error import ModelErrorField, field_covariance
from ._next_poses import DWELL_S, MIN_LEDS, base_configurations, distances_seen
from ._noise import NoiseModel, estimate_noise
from ._observation_noise import (
    observation_angles,
    observation_noise,
    observation_noise_source,
)
from ._poses import (
    PoseEstimate,
    chunked_led_variance,
    default_window,
    errors_against,
    estimate_poses,
    led_emission_angles,
)
from ._poses_io import read_poses, write_poses
from ._prior import GaussianPrior, no_prior, term_prior
from ._quoted_sigma import SOURCES as SIGMA_SOURCES, QuotedSigma, quoted_sigma, sigma_of
from ._registration import Registration, register_leds
from ._solve import (
    LeastSquares,
    Solution,
    composed,
    default_solver,
    gauss_newton_step,
    normal_at,
    padded_size,
    solve,
)
from ._static import static_segments
from ._uncertainty import (
    RCOND,
    column_scale,
    covariance,
    effective_clusters,
    identifiability,
    jackknife_covariance,
    robust_covariance,
    spd_inverse,
)
from ._weighting import (
    LedFeatures,
    get_weighting,
    register_weighting,
    weighting_needs,
    weighting_schemes,
)

__all__ = [
    "ClockAlignment",
    "align_clocks",
    "clock_effects",
    "robot_speeds",
    "stream_speeds",
    "tool_poses",
    "tracker_speeds",
    "ModelErrorField",
    "field_covariance",
    "QuotedSigma",
    "SIGMA_SOURCES",
    "quoted_sigma",
    "sigma_of",
    "NoiseModel",
    "estimate_noise",
    "observation_angles",
    "observation_noise",
    "observation_noise_source",
    "visible_frames",
    "distances_seen",
    "base_configurations",
    "DWELL_S",
    "MIN_LEDS",
    "RCOND",
    "GaussianPrior",
    "LeastSquares",
    "Solution",
    "column_scale",
    "covariance",
    "robust_covariance",
    "spd_inverse",
    "effective_clusters",
    "default_solver",
    "gauss_newton_step",
    "identifiability",
    "jackknife_covariance",
    "no_prior",
    "normal_at",
    "composed",
    "padded_size",
    "solve",
    "term_prior",
    "LedFeatures",
    "PoseEstimate",
    "Registration",
    "base_frame_poses",
    "chunked_led_variance",
    "led_emission_angles",
    "default_window",
    "errors_against",
    "estimate_poses",
    "get_weighting",
    "read_poses",
    "register_leds",
    "register_weighting",
    "static_segments",
    "weighting_needs",
    "weighting_schemes",
    "write_poses",
]
