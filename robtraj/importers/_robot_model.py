"""Robot models for a recording's `/robot`: a built-in name, a DH JSON file or a URDF file.

Everything becomes what `RobotLog` stores (docs/import.md, "Robot models"): a built-in
`model` name, or a standard-DH table ``[d, a, alpha, theta_offset]`` [m, m, rad, rad]
plus the flange (tool0) in the last DH frame and the link masses [kg].

A URDF's chain becomes an equivalent DH table in `_urdf_chain`.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from .._errors import UserError
from ..recording import Pose, RobotLog, limits_document
from ._common import _unit_scale, quat_wxyz
from ._urdf_chain import read_urdf_chain

_ANGLE_SCALES = {"rad": 1.0, "deg": np.pi / 180.0}
_JSON_KEYS = {
    "name",
    "dh",
    "unit",
    "angle_unit",
    "flange",
    "link_mass",
    "payload_mass",
    "joint_limits",
}


@dataclasses.dataclass(frozen=True)
class RobotDescription:
    """A robot as a recording stores it: a built-in `model` name, or a DH table.

    - `name`: the robot's name (built-in name, the URDF's ``<robot name>``, the JSON's
      ``"name"`` or the file name).
    - `model`: built-in model name, or None.
    - `dh`: `(J, 4)` rows ``[d, a, alpha, theta_offset]`` [m, m, rad, rad], or None.
    - `flange`: the flange (tool0) frame in the last DH frame (a `Pose` of shape `()`).
    - `link_mass`: `(J,)` [kg], or None (5 kg per link).
    - `joint_names`: the URDF's names of the chain's joints, in order (else empty).
    - `joint_limits`: `(J, 2)` [rad] each joint's range ``[lower, upper]`` (±inf: none on
      that side), or None (a built-in's own, else unlimited).
    """

    name: str
    model: str | None = None
    dh: np.ndarray | None = None
    flange: Pose | None = None
    link_mass: np.ndarray | None = None
    joint_names: tuple[str, ...] = ()
    payload_mass: float | None = None
    joint_limits: np.ndarray | None = None

    @property
    def n_joints(self) -> int:
        if self.dh is not None:
            return int(self.dh.shape[0])
        from ..model import BUILTIN_ROBOTS

        return BUILTIN_ROBOTS[self.model]().n_joints

    def robot_model(self):
        """The `robtraj.model.RobotModel` it describes."""
        from ..model import robot_from_log

        return robot_from_log(self.robot_log(np.zeros(0), np.zeros((0, self.n_joints))))

    def robot_log(self, time: np.ndarray, joints: np.ndarray) -> RobotLog:
        """The `RobotLog` of joint samples `joints` `(K, J)` [rad] at `time` `(K,)` [s]."""
        return RobotLog(
            time=time,
            joints=joints,
            model=self.model,
            dh=self.dh,
            flange=self.flange,
            link_mass=self.link_mass,
            payload_mass=self.payload_mass,
            joint_limits=self.joint_limits,
        )


def read_robot_model(
    spec: str | os.PathLike, *, flange_link: str | None = None, base_link: str | None = None
) -> RobotDescription:
    """The robot named by `spec`: a built-in name (``abb_irb2400_16``, ``ur10``), a DH JSON
    file or a URDF file (told apart by the extension, else by the first character).

    URDF only: `flange_link` names the flange link (default: ``tool0``, else ``flange``,
    else the last link of the chain); `base_link` the robot's base frame (default: the
    root link; it must be fixed to the root). `UserError` (one line) for bad input.
    """
    from ..model import BUILTIN_ROBOTS

    path = Path(spec)
    if str(spec) in BUILTIN_ROBOTS and not path.is_file():
        if flange_link is not None or base_link is not None:
            raise UserError("flange_link and base_link apply to URDF robot models only")
        return RobotDescription(name=str(spec), model=str(spec))
    if not path.is_file():
        names = ", ".join(sorted(BUILTIN_ROBOTS))
        raise UserError(f"{path}: no such robot model file (built-in models: {names})")
    text = path.read_text(encoding="utf-8", errors="replace")
    suffix = path.suffix.lower()
    is_json = suffix == ".json" or (suffix not in {".urdf", ".xml"} and text.lstrip()[:1] == "{")
    if is_json:
        if flange_link is not None or base_link is not None:
            raise UserError("flange_link and base_link apply to URDF robot models only")
        return _read_dh_json(path, text)
    chain = read_urdf_chain(path, flange_link=flange_link, base_link=base_link)
    rot = Rotation.from_matrix(chain.last_from_flange[:3, :3])
    return RobotDescription(
        name=chain.name,
        dh=chain.dh,
        flange=Pose(chain.last_from_flange[:3, 3] + 0.0, quat_wxyz(rot)),
        link_mass=chain.link_mass,
        payload_mass=chain.payload_mass,
        joint_names=chain.joint_names,
        joint_limits=chain.joint_limits,
    )


def write_robot_model(
    robot: RobotDescription,
    path: str | os.PathLike,
    *,
    unit: str = "m",
    angle_unit: str = "rad",
) -> Path:
    """Write `robot` as a DH JSON file (a built-in model with its own DH table, flange,
    link masses and joint limits); returns the path."""
    scale = _unit_scale(unit, "write_robot_model")
    if angle_unit not in _ANGLE_SCALES:
        raise UserError(f"angle unit {angle_unit!r} is not one of rad, deg")
    ang = _ANGLE_SCALES[angle_unit]
    dh, flange, mass, limits = robot.dh, robot.flange, robot.link_mass, robot.joint_limits
    if dh is None:
        from ..model import BUILTIN_ROBOTS

        model = BUILTIN_ROBOTS[robot.model]()
        dh, wxyz_xyz = np.asarray(model.dh), np.asarray(model.last_from_flange)
        flange = Pose(wxyz_xyz[4:], wxyz_xyz[:4]) if flange is None else flange
        mass = np.asarray(model.link_mass) if mass is None else mass
        if limits is None and model.joint_limits is not None:
            limits = np.asarray(model.joint_limits)
        if robot.payload_mass is None:
            robot = dataclasses.replace(robot, payload_mass=float(model.payload_mass))
    rows = np.array(dh, np.float64)
    rows[:, :2] /= scale
    rows[:, 2:] /= ang
    doc: dict = {"name": robot.name, "unit": unit, "angle_unit": angle_unit, "dh": rows.tolist()}
    if flange is not None:
        doc["flange"] = {
            "position": (np.asarray(flange.position, np.float64) / scale).tolist(),
            "quaternion_wxyz": np.asarray(flange.quaternion_wxyz, np.float64).tolist(),
        }
    if mass is not None:
        doc["link_mass"] = np.asarray(mass, np.float64).tolist()
    if robot.payload_mass is not None:
        doc["payload_mass"] = float(robot.payload_mass)
    if limits is not None:
        doc["joint_limits"] = limits_document(limits, ang)
    path = Path(path)
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def _read_dh_json(path: Path, text: str) -> RobotDescription:
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise UserError(f"{path}: not valid JSON ({e})") from None
    return robot_description(doc, path)


def robot_description(doc: Any, path: str | Path = "robot") -> RobotDescription:
    """The robot of a parsed DH JSON document (or ``{"model": name}`` for a built-in, as a
    CALIB.json's ``"robot"`` holds it); `path` names it in errors."""
    if isinstance(doc, dict) and set(doc) == {"model"}:
        from ..model import BUILTIN_ROBOTS

        if doc["model"] not in BUILTIN_ROBOTS:
            raise UserError(f"{path}: unknown built-in robot model {doc['model']!r}")
        return RobotDescription(name=str(doc["model"]), model=str(doc["model"]))
    if not isinstance(doc, dict) or "dh" not in doc:
        raise UserError(f'{path}: a DH robot model is a JSON object with a "dh" table')
    unknown = sorted(set(doc) - _JSON_KEYS)
    if unknown:
        raise UserError(
            f"{path}: unknown key {unknown[0]!r} (known: {', '.join(sorted(_JSON_KEYS))})"
        )
    scale = _unit_scale(doc.get("unit", "m"), path)
    angle_unit = doc.get("angle_unit", "rad")
    if angle_unit not in _ANGLE_SCALES:
        raise UserError(f"{path}: angle_unit {angle_unit!r} is not one of rad, deg")
    rows = doc["dh"]
    if not isinstance(rows, list) or not rows:
        raise UserError(f'{path}: "dh" must be a list of at least one row [d, a, alpha, theta]')
    for i, row in enumerate(rows):
        if not isinstance(row, list) or len(row) != 4:
            n = len(row) if isinstance(row, list) else "no list of"
            raise UserError(
                f"{path}: dh row {i} has {n} numbers, expected 4 [d, a, alpha, theta_offset]"
            )
    dh = _numbers(rows, path, "dh")
    dh[:, :2] *= scale
    dh[:, 2:] *= _ANGLE_SCALES[angle_unit]
    if np.any(np.abs(dh[:, :2]) > 50.0):
        raise UserError(f'{path}: a DH length exceeds 50 m; millimetres need "unit": "mm"')
    if angle_unit == "rad" and np.any(np.abs(dh[:, 2:]) > 2 * np.pi + 1e-9):
        raise UserError(f'{path}: a DH angle exceeds 2π rad; degrees need "angle_unit": "deg"')
    flange = None
    if "flange" in doc:
        flange = _flange_member(doc["flange"], scale, path)
    mass = None
    if "link_mass" in doc:
        mass = _numbers(doc["link_mass"], path, "link_mass")
        if mass.shape != (dh.shape[0],) or np.any(mass < 0):
            raise UserError(
                f"{path}: link_mass must hold {dh.shape[0]} masses >= 0 [kg], one per DH row"
            )
    payload = None
    if "payload_mass" in doc:
        payload = _numbers([doc["payload_mass"]], path, "payload_mass")[0]
        if not payload >= 0:
            raise UserError(f"{path}: payload_mass must be a mass >= 0 [kg]")
    limits = None
    if "joint_limits" in doc:
        limits = _limits_member(doc["joint_limits"], dh.shape[0], _ANGLE_SCALES[angle_unit], path)
    name = str(doc.get("name", Path(path).stem))
    return RobotDescription(
        name=name, dh=dh, flange=flange, link_mass=mass, payload_mass=payload, joint_limits=limits
    )


def _numbers(value, path: str | Path, key: str) -> np.ndarray:
    try:
        out = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{path}: {key} must hold numbers only") from None
    if not np.all(np.isfinite(out)):
        raise UserError(f"{path}: {key} holds a non-finite number")
    return out


def _limits_member(value, n_joints: int, scale: float, path: str | Path) -> np.ndarray:
    """`(J, 2)` [rad] from ``"joint_limits"``: per joint ``[lower, upper]`` in the angle
    unit, a null bound (or a null row) for none on that side."""
    rows = value if isinstance(value, list) else None
    if rows is None or len(rows) != n_joints:
        raise UserError(
            f"{path}: joint_limits must hold {n_joints} rows [lower, upper], one per DH row"
        )
    out = np.empty((n_joints, 2))
    for i, row in enumerate(rows):
        row = [None, None] if row is None else row
        if not isinstance(row, list) or len(row) != 2:
            raise UserError(f"{path}: joint_limits row {i} must be [lower, upper] (null: none)")
        for k, (bound, none) in enumerate(zip(row, (-np.inf, np.inf), strict=True)):
            out[i, k] = (
                none if bound is None else _numbers([bound], path, "joint_limits")[0] * scale
            )
        if not out[i, 0] <= out[i, 1]:
            raise UserError(f"{path}: joint_limits row {i} has lower > upper")
    return out


def _flange_member(value, scale: float, path: str | Path) -> Pose:
    if not isinstance(value, dict) or set(value) != {"position", "quaternion_wxyz"}:
        raise UserError(f'{path}: "flange" must be {{"position": [..], "quaternion_wxyz": [..]}}')
    position = _numbers(value["position"], path, "flange position") * scale
    quat = _numbers(value["quaternion_wxyz"], path, "flange quaternion_wxyz")
    if position.shape != (3,) or quat.shape != (4,):
        raise UserError(f"{path}: flange needs a position of 3 and a quaternion_wxyz of 4 numbers")
    norm = np.linalg.norm(quat)
    if abs(norm - 1.0) > 1e-6:
        raise UserError(f"{path}: flange quaternion_wxyz is not unit (norm {norm:.9g})")
    return Pose(position, quat / norm)
