"""A robot program's targets from a CSV or JSON file (the `/program` of a recording).

Targets are TCP poses in the robot's base frame. CSV: a header row, then one row per
target; columns (case does not matter):

- position: ``x, y, z`` [m] or ``x_mm, y_mm, z_mm`` [mm];
- orientation, one of: ``qw, qx, qy, qz`` (unit quaternion); ``rx, ry, rz`` (rotation
  vector [rad], as Universal Robots give poses); ``a, b, c`` [deg] (KUKA: R = Rz(a)·Ry(b)·Rx(c));
- ``motion``: ``start``, ``linear`` or ``joint`` (also ``LIN``/``MoveL``, ``PTP``/``MoveJ``);
  default ``joint``, and the first target is always ``start``;
- ``speed`` [m/s] or ``speed_mm_s`` [mm/s]: commanded TCP speed to the target (default 0);
- optional ``label`` (name of the pose, e.g. ``P1``) and ``cycle`` (integer).

JSON: ``{"unit": "m"|"mm", "targets": [{"position": [..], "quaternion_wxyz": [..]
(or "rotvec": [..] [rad], or "abc_deg": [..]), "motion": .., "speed": .. [m/s],
"label": .., "cycle": ..}, ..]}``.
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from .._errors import UserError
from ..recording import Pose, Program
from ._common import _unit_scale, quat_wxyz

_MOTIONS = {
    "start": "start",
    "linear": "linear",
    "lin": "linear",
    "movel": "linear",
    "joint": "joint",
    "ptp": "joint",
    "movej": "joint",
}


def read_program(path: str | os.PathLike) -> tuple[Program, dict[str, np.ndarray]]:
    """The program in `path` (CSV or JSON, by extension) and its optional per-target
    ``label`` (str) and ``cycle`` (int) columns, which the schema keeps beside it."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such program file")
    if path.suffix.lower() == ".json":
        rows, scale = _json_rows(path)
    else:
        rows, scale = _csv_rows(path), 1.0
    if len(rows) < 2:
        raise UserError(f"{path}: a program needs at least two targets, found {len(rows)}")
    return _program(rows, scale, path)


def _csv_rows(path: Path) -> list[dict]:
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: not a readable CSV program ({e})") from None
    try:
        dialect = csv.Sniffer().sniff(text.splitlines()[0], delimiters=",;\t ")
    except (csv.Error, IndexError):
        dialect = csv.excel
    reader = csv.DictReader(text.splitlines(), dialect=dialect)
    if reader.fieldnames is None:
        raise UserError(f"{path}: empty program file")
    rows = []
    for row in reader:
        rows.append({(k or "").strip().lower(): (v or "").strip() for k, v in row.items()})
    return [r for r in rows if any(r.values())]


def _json_rows(path: Path) -> tuple[list[dict], float]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise UserError(f"{path}: not a readable JSON program ({e})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("targets"), list):
        raise UserError(f"{path}: a JSON program needs a list 'targets'")
    scale = _unit_scale(str(doc.get("unit", "m")), path)
    rows = []
    for t in doc["targets"]:
        if not isinstance(t, dict) or "position" not in t:
            raise UserError(f"{path}: every target needs a 'position'")
        row = {k: v for k, v in t.items() if k not in ("position", "quaternion_wxyz")}
        row.update(zip(("x", "y", "z"), _vector(t["position"], 3, path, "position")))
        for key, cols in (
            ("quaternion_wxyz", ("qw", "qx", "qy", "qz")),
            ("rotvec", ("rx", "ry", "rz")),
            ("abc_deg", ("a", "b", "c")),
        ):
            if key in t:
                row.update(zip(cols, _vector(t[key], len(cols), path, key)))
        rows.append(row)
    return rows, scale


def _vector(value, n: int, path: Path, name: str) -> list:
    if not isinstance(value, list) or len(value) != n:
        raise UserError(f"{path}: '{name}' must be a list of {n} numbers")
    return value


def _numbers(rows: list[dict], cols: tuple[str, ...], path: Path) -> np.ndarray:
    try:
        return np.array([[float(r[c]) for c in cols] for r in rows], np.float64)
    except (KeyError, TypeError, ValueError):
        for i, r in enumerate(rows):
            for c in cols:
                try:
                    float(r[c])
                except (KeyError, TypeError, ValueError):
                    raise UserError(
                        f"{path}: target {i + 1} has no number in column {c!r}"
                    ) from None
        raise


def _has(rows: list[dict], cols: tuple[str, ...]) -> bool:
    return all(c in rows[0] for c in cols)


def _program(rows: list[dict], scale: float, path: Path) -> tuple[Program, dict]:
    if _has(rows, ("x_mm", "y_mm", "z_mm")):
        position = _numbers(rows, ("x_mm", "y_mm", "z_mm"), path) * 1e-3
    elif _has(rows, ("x", "y", "z")):
        position = _numbers(rows, ("x", "y", "z"), path) * scale
    else:
        raise UserError(f"{path}: no position columns (x, y, z or x_mm, y_mm, z_mm)")
    if _has(rows, ("qw", "qx", "qy", "qz")):
        q = _numbers(rows, ("qw", "qx", "qy", "qz"), path)
        norm = np.linalg.norm(q, axis=1)
        if np.any(np.abs(norm - 1.0) > 1e-3):
            i = int(np.argmax(np.abs(norm - 1.0)))
            raise UserError(f"{path}: target {i + 1}'s quaternion is not of unit length")
        rot = Rotation.from_quat(q[:, [1, 2, 3, 0]])
    elif _has(rows, ("rx", "ry", "rz")):
        rot = Rotation.from_rotvec(_numbers(rows, ("rx", "ry", "rz"), path))
    elif _has(rows, ("a", "b", "c")):
        rot = Rotation.from_euler("ZYX", _numbers(rows, ("a", "b", "c"), path), degrees=True)
    else:
        raise UserError(f"{path}: no orientation columns (qw, qx, qy, qz; rx, ry, rz; or a, b, c)")
    motion = []
    for i, r in enumerate(rows):
        word = str(r.get("motion", "joint") or "joint").strip().lower()
        if word not in _MOTIONS:
            raise UserError(
                f"{path}: target {i + 1} has motion {word!r} (known: start, linear, joint)"
            )
        motion.append(_MOTIONS[word])
    motion[0] = "start"
    if "speed_mm_s" in rows[0]:
        speed = _numbers(rows, ("speed_mm_s",), path)[:, 0] * 1e-3
    elif "speed" in rows[0]:
        speed = _numbers(rows, ("speed",), path)[:, 0]
    else:
        speed = np.zeros(len(rows))
    if not np.all(np.isfinite(position)) or not np.all(np.isfinite(speed)) or np.any(speed < 0):
        raise UserError(f"{path}: positions must be finite and speeds finite and not negative")
    extra = {}
    if "label" in rows[0]:
        extra["label"] = np.array([str(r.get("label", "")) for r in rows])
    if "cycle" in rows[0]:
        extra["cycle"] = _numbers(rows, ("cycle",), path)[:, 0].astype(np.int32)
    program = Program(targets=Pose(position, quat_wxyz(rot)), motion=np.array(motion), speed=speed)
    return program, extra


def program_csv(program: Program, labels: np.ndarray | None = None) -> str:
    """`program` as the CSV `read_program` reads: metres, unit quaternions, m/s."""
    lines = ["label,x,y,z,qw,qx,qy,qz,motion,speed"]
    p, q = program.targets.position, program.targets.quaternion_wxyz
    for i in range(p.shape[0]):
        label = "" if labels is None else str(labels[i])
        nums = ",".join(repr(float(v)) for v in (*p[i], *q[i]))
        lines.append(f"{label},{nums},{program.motion[i]},{float(program.speed[i])!r}")
    return "\n".join(lines) + "\n"
