"""A calibration carried to the cell's tools: the calibrated robot as URDF, every
parameter with its σ as JSON (`robtraj export`).

The URDF holds the calibrated geometry: joint zero offsets, DH length and twist errors
and Hayati's tilts go into the joint origins, the calibrated flange←tool into a fixed
``tool`` link. What a URDF cannot hold (compliance, backlash, dictionary terms and
joint angle error maps, tracker and clock effects) is listed in the file and by
`not_representable`.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import numpy as np

from ..model import RobotModel, dh_corrections, effect_component_names, pose_se3, urdf_text

#: the effects a URDF's joint origins carry
GEOMETRIC = ("joint_offset", "link_length", "link_twist")
#: effects of the measurement, not of the robot
OF_THE_MEASUREMENT = ("time_offset", "tracker_scale", "thermal_drift", "led_angle_bias")


def calibrated_geometry(calib, robot: RobotModel) -> tuple[RobotModel, np.ndarray]:
    """`robot` with the calibration's geometric effects in its DH table (Δd, Δa, Δα and
    the joint offsets in θ₀) and Hayati's tilts `(joints,)` [rad]: its forward kinematics
    with those tilts is the calibrated geometric model."""
    effects = calib.effects_module(robot.n_joints)
    dh_delta, tilt = dh_corrections(robot, effects)
    dh = robot.dh + dh_delta.at[:, 3].add(effects.joint_offset)
    return eqx.tree_at(lambda r: r.dh, robot, dh), np.asarray(tilt)


def not_representable(calib) -> list[str]:
    """Effects of `calib` with a value that the URDF does not carry, each with why."""
    out = []
    for name, value in calib.effects.items():
        if name in GEOMETRIC or not np.any(np.asarray(value, float) != 0):
            continue
        why = "of the measurement, not the robot" if name in OF_THE_MEASUREMENT else "not geometry"
        out.append(f"{name} ({why})")
    return out


def calibration_urdf(calib, robot: RobotModel) -> str:
    """URDF text of the calibrated robot (links ``base_link`` … ``tool0``, and ``tool``
    at the calibrated flange←tool)."""
    geometry, tilt = calibrated_geometry(calib, robot)
    tool = pose_se3(calib.flange_from_tool).as_matrix()
    missing = not_representable(calib)
    notes = (
        f"robtraj calibration of {robot.name}: joint offsets, link lengths and twists in the "
        "joint origins; tool = the calibrated flange<-tool",
        "not representable in URDF: " + (", ".join(missing) if missing else "nothing"),
    )
    return urdf_text(geometry, tilt=tilt, flange_from_tool=np.asarray(tool), notes=notes)


def parameter_document(calib) -> dict[str, Any]:
    """Every parameter of `calib` with its σ (SI units): the rigid transforms (σ of the
    tangent-space components ``tx … rz``), each effect entry (maps: each knot), the
    constellation, and the robot calibrated."""
    sigma = calib.sigma

    def sig(names):
        return [_finite(sigma.get(n, 0.0)) for n in names]

    def pose(p, name):
        comps = [f"{name}.{c}" for c in ("tx", "ty", "tz", "rx", "ry", "rz")]
        return {
            "position": np.asarray(p.position).tolist(),
            "quaternion_wxyz": np.asarray(p.quaternion_wxyz).tolist(),
            "sigma": dict(zip([c.split(".")[1] for c in comps], sig(comps), strict=True)),
        }

    effects = {}
    for name, value in calib.effects.items():
        v = np.asarray(value, float)
        names = effect_component_names(name, v.shape)
        effects[name] = {
            "value": v.tolist(),
            "sigma": np.reshape(np.array(sig(names), dtype=object), v.shape).tolist(),
            "estimated": name in calib.estimated,
            "components": names,
        }
    leds = [int(i) for i in calib.led_ids]
    return {
        "robot": calib.robot or None,
        "camera_from_base": pose(calib.camera_from_base, "camera_from_base"),
        "flange_from_tool": pose(calib.flange_from_tool, "flange_from_tool"),
        "effects": effects,
        "constellation": {
            "led_ids": leds,
            "positions": np.asarray(calib.constellation).tolist(),
            "sigma": [sig([f"constellation[LED {i}].{c}" for c in "xyz"]) for i in leds],
        },
        "residual_rms_m": calib.residual_rms_m,
        "not_in_urdf": not_representable(calib),
    }


def _finite(x: float) -> float | None:
    """σ as JSON: None where the recording does not determine the parameter (inf)."""
    return float(x) if np.isfinite(x) else None
