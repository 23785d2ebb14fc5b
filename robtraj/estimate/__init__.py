"""Estimation: static segments, LED registration, weighting schemes, per-frame poses.

Bundle calibration lives in `robtraj.estimate.calibration`.
"""

from ._poses import (
    PoseEstimate,
    chunked_led_variance,
    default_window,
    errors_against,
    estimate_poses,
)
from ._poses_io import read_poses, write_poses
from ._registration import Registration, register_leds
from ._static import static_segments
from ._weighting import (
    LedFeatures,
    get_weighting,
    register_weighting,
    weighting_needs,
    weighting_schemes,
)

__all__ = [
    "LedFeatures",
    "PoseEstimate",
    "Registration",
    "chunked_led_variance",
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
