"""The forward measurement model, pure JAX and differentiable (DESIGN sections 5 and 7).

One model, used by the simulator to generate and by the estimators to fit: robot
kinematics (standard DH), the LED tool, the camera (volume, visibility, noise) and
the effect library.
"""

from ._camera import CameraModel, emission_angle, in_volume, noise_sigma
from ._dictionary import (
    HARMONICS,
    Term,
    amplitude_phase,
    default_terms,
    describe,
    dictionary,
    register_effect,
    term,
    unregister_effect,
)
from ._effects import (
    BIAS_REFERENCE_ANGLE,
    EFFECT_NAMES,
    LIBRARY,
    Effects,
    effect_component_names,
    is_effect,
    known_effects,
    parse_effect,
)
from ._kinematics import (
    BUILTIN_ROBOTS,
    RobotModel,
    abb_irb2400_16,
    flange_jacobian,
    forward_kinematics,
    gravity_torque,
    inverse_kinematics,
    joint_frames,
    redundant_link_parameters,
    robot_from_log,
    ur10,
)
from ._measurement import (
    MOTION_THRESHOLD,
    camera_from_base_at,
    dh_corrections,
    effective_joints,
    flange_poses,
    interpolate_joints,
    led_positions,
    motion_direction,
    motion_sign,
    predict_tool_poses,
)
from ._tool import hemispherical_tool

__all__ = [
    "BIAS_REFERENCE_ANGLE",
    "BUILTIN_ROBOTS",
    "CameraModel",
    "EFFECT_NAMES",
    "MOTION_THRESHOLD",
    "HARMONICS",
    "Effects",
    "LIBRARY",
    "RobotModel",
    "Term",
    "abb_irb2400_16",
    "amplitude_phase",
    "camera_from_base_at",
    "default_terms",
    "describe",
    "dh_corrections",
    "dictionary",
    "effect_component_names",
    "effective_joints",
    "emission_angle",
    "flange_jacobian",
    "flange_poses",
    "forward_kinematics",
    "gravity_torque",
    "hemispherical_tool",
    "in_volume",
    "interpolate_joints",
    "inverse_kinematics",
    "is_effect",
    "joint_frames",
    "known_effects",
    "led_positions",
    "motion_direction",
    "motion_sign",
    "noise_sigma",
    "parse_effect",
    "predict_tool_poses",
    "redundant_link_parameters",
    "register_effect",
    "robot_from_log",
    "term",
    "unregister_effect",
    "ur10",
]
