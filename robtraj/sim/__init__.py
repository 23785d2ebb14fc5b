"""The simulator: scenarios, robot motion, effects, visibility and noise → Recording."""

from ._campaign import CONTROLLER_EPOCH, CampaignFiles, write_campaign
from ._motion import Move, trapezoid_duration, trapezoid_progress
from ._scenarios import (
    DEFAULT_DURATION,
    ISO_CUBE_CENTRE,
    ISO_CUBE_SIDE,
    SCENARIOS,
    iso_cube_corner_truth,
    iso_cube_cycles,
    iso_cube_poses,
    iso_cube_truth,
)
from ._simulate import (
    TWIN_AMPLITUDE,
    SimulatedFile,
    calibration_twin,
    joint_dwells,
    simulate,
    simulate_to,
)
from ._static_poses import POSE_NOISE, UR10_RANGES, static_pose_series
from ._unmodelled import (
    CrossJointError,
    PeriodicJointError,
    SightLineBias,
    VelocityDeadbandError,
    joint_harmonics,
)

__all__ = [
    "CONTROLLER_EPOCH",
    "CampaignFiles",
    "CrossJointError",
    "write_campaign",
    "DEFAULT_DURATION",
    "ISO_CUBE_CENTRE",
    "ISO_CUBE_SIDE",
    "Move",
    "PeriodicJointError",
    "SightLineBias",
    "VelocityDeadbandError",
    "SCENARIOS",
    "SimulatedFile",
    "TWIN_AMPLITUDE",
    "calibration_twin",
    "iso_cube_corner_truth",
    "iso_cube_cycles",
    "iso_cube_poses",
    "iso_cube_truth",
    "joint_dwells",
    "joint_harmonics",
    "simulate",
    "simulate_to",
    "static_pose_series",
    "POSE_NOISE",
    "UR10_RANGES",
    "trapezoid_duration",
    "trapezoid_progress",
]
