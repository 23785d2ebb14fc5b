"""Reading CALIB.json (DESIGN section 8): the one schema-checked loader every command uses.

A calibration may come from `robtraj calibrate` or from another source; the loader checks
the fields the analysis needs and turns every defect into one `UserError` naming the field:

- ``camera_from_base``, ``flange_from_tool``: ``{"position": [x, y, z] (m),
  "quaternion_wxyz": [w, x, y, z]}``, finite; a quaternion of norm 0 is refused, one off
  unit norm by more than 1e-3 too (rounding below that is normalised away);
- ``constellation``: ``{"led_ids": [..], "positions": [[x, y, z], ..] (m, tool frame)}``,
  at least 3 distinct LEDs;
- optional: ``time_offset`` (s), ``residual_rms_m`` and ``noise_sigma_m`` (m, >= 0 or
  null), ``effects`` (names of `robtraj.model.known_effects`, finite values), ``covariance``
  (null, or ``{"parameters": [..], "matrix": [[..]]}`` square of that size, finite),
  ``identifiability`` (an object; its ``undetermined``, if given, a list of parameter
  names the calibration's recording did not determine: the analyses warn about them),
  ``schema_version`` (1 when absent; another than this robtraj reads is refused),
  ``maps`` (per joint angle error map in ``effects``: which knots were estimated, their σ,
  the joint range fitted), ``provenance`` (the command that made it, the effects named).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ._errors import UserError

_UNIT_TOLERANCE = 1e-3


def _numbers(value: Any, shape: tuple[int, ...] | None, where: str) -> np.ndarray:
    """`value` as a finite float array of `shape` (None: any), or `UserError` naming `where`."""
    if isinstance(value, (str, bytes, dict)) or value is None:
        raise UserError(f"{where} must be numbers, got {type(value).__name__}")
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where} must be numbers, got {json.dumps(value)[:60]}") from None
    if shape is not None and a.shape != shape:
        want = "×".join(map(str, shape)) or "a single number"
        raise UserError(f"{where} must be {want}, got shape {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise UserError(f"{where} holds a non-finite value")
    return a


def _pose(doc: dict, key: str) -> dict:
    p = doc.get(key)
    if not isinstance(p, dict):
        raise UserError(f"'{key}' must be an object with position and quaternion_wxyz")
    for field in ("position", "quaternion_wxyz"):
        if field not in p:
            raise UserError(f"'{key}' lacks '{field}'")
    t = _numbers(p["position"], (3,), f"{key}.position")
    q = _numbers(p["quaternion_wxyz"], (4,), f"{key}.quaternion_wxyz")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > _UNIT_TOLERANCE:
        raise UserError(f"{key}.quaternion_wxyz has norm {norm:.6g}; a rotation needs norm 1")
    return {"position": t.tolist(), "quaternion_wxyz": (q / norm).tolist()}


def _constellation(doc: dict) -> dict:
    c = doc.get("constellation")
    if not isinstance(c, dict) or "led_ids" not in c or "positions" not in c:
        raise UserError("'constellation' must be an object with led_ids and positions")
    ids = _numbers(c["led_ids"], None, "constellation.led_ids")
    if ids.ndim != 1 or np.any(ids != np.round(ids)) or np.any(ids < 0):
        raise UserError("constellation.led_ids must be a list of non-negative integers")
    if len(set(ids.tolist())) != ids.size:
        raise UserError("constellation.led_ids repeats an LED id")
    if ids.size < 3:
        raise UserError(f"constellation has {ids.size} LEDs; a tool pose needs at least 3")
    pos = _numbers(c["positions"], (ids.size, 3), "constellation.positions")
    return {"led_ids": ids.astype(int).tolist(), "positions": pos.tolist()}


def _optional_number(doc: dict, key: str, *, nonnegative: bool = False) -> float | None:
    v = doc.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise UserError(f"'{key}' must be a finite number or null, got {json.dumps(v)[:40]}")
    if nonnegative and v < 0:
        raise UserError(f"'{key}' must be >= 0, got {v}")
    return float(v)


def _effects(doc: dict) -> dict:
    from .model import EFFECT_NAMES, is_effect

    e = doc.get("effects") or {}
    if not isinstance(e, dict):
        raise UserError("'effects' must be an object {name: value}")
    unknown = sorted(n for n in e if not is_effect(n))
    if unknown:
        raise UserError(
            f"unknown effect(s) {', '.join(unknown)} "
            f"(known: {', '.join(EFFECT_NAMES)} and the dictionary's terms)"
        )
    return {k: _numbers(v, None, f"effects.{k}").tolist() for k, v in e.items()}


def _covariance(doc: dict) -> dict | None:
    cov = doc.get("covariance")
    if cov is None:
        return None
    if not isinstance(cov, dict) or "parameters" not in cov or "matrix" not in cov:
        raise UserError("'covariance' must be null or an object with parameters and matrix")
    names = cov["parameters"]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise UserError("covariance.parameters must be a list of names")
    m = _numbers(cov["matrix"], (len(names), len(names)), "covariance.matrix")
    return {"parameters": names, "matrix": m.tolist()}


def _covariance_robust(doc: dict, cov: dict | None) -> dict | None:
    rob = doc.get("covariance_robust")
    if rob is None:
        return None
    n = 0 if cov is None else len(cov["parameters"])
    if not isinstance(rob, dict) or "matrix" not in rob or cov is None:
        raise UserError(
            "'covariance_robust' must be null or an object with a matrix beside a covariance"
        )
    m = _numbers(rob["matrix"], (n, n), "covariance_robust.matrix")
    clusters = rob.get("clusters", 0)
    if not isinstance(clusters, int) or isinstance(clusters, bool) or clusters < 0:
        raise UserError("covariance_robust.clusters must be a whole number ≥ 0")
    eff = rob.get("effective_clusters")
    if eff is not None:
        if not isinstance(eff, list) or len(eff) != n:
            raise UserError(f"covariance_robust.effective_clusters must list {n} numbers or nulls")
        eff = [
            None
            if x is None
            else float(_numbers([x], (1,), "covariance_robust.effective_clusters")[0])
            for x in eff
        ]
    return {"matrix": m.tolist(), "clusters": clusters, "effective_clusters": eff}


def _covariance_field(doc: dict, cov: dict | None) -> dict | None:
    field = doc.get("covariance_field")
    if field is None:
        return None
    if not isinstance(field, dict) or "matrix" not in field or cov is None:
        raise UserError(
            "'covariance_field' must be null or an object with a matrix beside a covariance"
        )
    n = len(cov["parameters"])
    m = _numbers(field["matrix"], (n, n), "covariance_field.matrix")
    model_error = field.get("model_error") or {}
    if not isinstance(model_error, dict):
        raise UserError("covariance_field.model_error must be an object")
    return {"matrix": m.tolist(), "model_error": model_error}


def _check_version(doc: dict) -> None:
    from .estimate.calibration import READABLE_VERSIONS, SCHEMA_VERSION

    v = doc.get("schema_version", 1)
    if isinstance(v, bool) or not isinstance(v, int) or v not in READABLE_VERSIONS:
        raise UserError(
            f"schema_version {json.dumps(v)[:20]}: this robtraj reads CALIB.json versions "
            f"{', '.join(map(str, READABLE_VERSIONS))} (writes {SCHEMA_VERSION}); "
            "write it again with this robtraj or use the robtraj that wrote it"
        )


def _maps(doc: dict) -> None:
    maps = doc.get("maps") or {}
    if not isinstance(maps, dict):
        raise UserError("'maps' must be an object {joint{j}_map: {...}}")
    effects = doc.get("effects") or {}
    for name, m in maps.items():
        if name not in effects:
            raise UserError(f"maps.{name} describes a map that is not in 'effects'")
        if not isinstance(m, dict) or "estimated" not in m:
            raise UserError(f"maps.{name} must be an object with 'estimated'")
        n = np.size(effects[name])
        if not isinstance(m["estimated"], list) or len(m["estimated"]) != n:
            raise UserError(f"maps.{name}.estimated must list {n} booleans, one per knot")
        rng = m.get("fitted_range_rad")
        if rng is not None:
            _numbers(rng, (2,), f"maps.{name}.fitted_range_rad")


def parse_calibration(doc: Any, name: str = "CALIB.json"):
    """A `CalibrationResult` from the parsed JSON `doc`; `UserError` (prefixed `name`) on any
    schema defect."""
    from .estimate.calibration import CalibrationResult

    try:
        if not isinstance(doc, dict):
            raise UserError(f"must hold a JSON object, not a {type(doc).__name__}")
        _check_version(doc)
        clean = dict(doc)
        clean["camera_from_base"] = _pose(doc, "camera_from_base")
        clean["flange_from_tool"] = _pose(doc, "flange_from_tool")
        clean["constellation"] = _constellation(doc)
        clean["effects"] = _effects(doc)
        _maps(clean)
        for key in ("time_offset", "residual_rms_m", "noise_sigma_m"):
            v = _optional_number(doc, key, nonnegative=key != "time_offset")
            clean.pop(key, None)
            if v is not None:
                clean[key] = v
        cov = _covariance(doc)
        clean.pop("covariance", None)
        if cov is not None:
            clean["covariance"] = cov
        clean.pop("covariance_robust", None)
        robust = _covariance_robust(doc, cov)
        if robust is not None:
            clean["covariance_robust"] = robust
        clean.pop("covariance_field", None)
        field = _covariance_field(doc, cov)
        if field is not None:
            clean["covariance_field"] = field
        ident = doc.get("identifiability", {})
        if not isinstance(ident, dict):
            raise UserError("'identifiability' must be an object")
        und = ident.get("undetermined", [])
        if not isinstance(und, list) or not all(isinstance(n, str) for n in und):
            raise UserError("identifiability.undetermined must be a list of parameter names")
        if doc.get("robot") is not None and not isinstance(doc["robot"], dict):
            raise UserError("'robot' must be an object (a DH JSON document or {\"model\": name})")
        gauge = doc.get("gauge")
        if isinstance(gauge, dict) and "reference_constellation" in gauge:
            ref = _numbers(gauge["reference_constellation"], None, "gauge.reference_constellation")
            if ref.ndim != 2 or ref.shape[1:] != (3,):
                raise UserError("gauge.reference_constellation must be a list of [x, y, z]")
        return CalibrationResult.from_json(clean)
    except UserError as e:
        raise UserError(f"{name}: {e}") from None


def load_calibration(path: str | Path):
    """Read and check a CALIB.json file (module docstring); `UserError` on any defect."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file (run `robtraj calibrate` first)")
    if not path.is_file():
        raise UserError(f"{path}: not a file")
    raw = path.read_bytes()
    if raw.startswith(b"\x89HDF"):
        raise UserError(f"{path}: an HDF5 file, not a CALIB.json (from `robtraj calibrate`)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text file, so not a CALIB.json") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise UserError(f"{path}: not JSON ({e.msg} at line {e.lineno})") from None
    except RecursionError:
        raise UserError(f"{path}: JSON nested too deeply") from None
    return parse_calibration(doc, str(path))


def check_robot(calib, rec, name: str = "CALIB.json") -> None:
    """`UserError` when `rec` (a `Recording`) logs another robot model than the one
    `calib` calibrated (`check_robot_model`). A calibration that does not name its
    robot (an older CALIB.json) is not checked."""
    if not calib.robot or rec.robot is None:
        return
    from .model import robot_from_log

    check_robot_model(calib, robot_from_log(rec.robot), name, "the recording")


def check_robot_model(calib, robot, name: str = "CALIB.json", whose: str = "the program") -> None:
    """`UserError` when `robot` (a `RobotModel`, `whose` it is) is another robot model
    than the one `calib` calibrated: another joint count, DH table or flange (1e-9
    m/rad); not checked where `calib` does not name its robot."""
    if not calib.robot:
        return
    from .importers import robot_description

    ours = robot_description(calib.robot, f"{name}: robot").robot_model()
    same = ours.dh.shape == robot.dh.shape and all(
        np.allclose(np.asarray(a), np.asarray(b), rtol=0.0, atol=1e-9)
        for a, b in ((ours.dh, robot.dh), (ours.last_from_flange, robot.last_from_flange))
    )
    if not same:
        raise UserError(
            f"{name} calibrated robot {ours.name!r} ({ours.n_joints} joints); {whose} "
            f"uses {robot.name!r} ({robot.n_joints} joints), another robot (DH table or "
            "flange): a calibration holds only for the robot model it was made on"
        )
