"""6-DOF pose measurements in CSV (laser tracker with a 6-DOF probe, static robot poses).

A *mapping* says which columns hold what, in which units and rotation convention::

    {
      "delimiter": ";", "decimal": ",",
      "measured":  {"position": ["x", "y", "z"], "position_unit": "mm",
                    "rotation": ["rx", "ry", "rz"], "angle_unit": "deg", "euler": "XYZ"},
      "measured_std": {"position": [..3 cols..], "rotation": [..3 cols..], "optional": true},
      "commanded": [ {"position": [..], "position_unit": "m",
                      "rotation": [..], "angle_unit": "rad", "euler": "xyz"},
                     {"position": [..], "quaternion_xyzw": [..4 cols..]} ],
      "joints": {"columns": [..], "angle_unit": "rad", "model": "ur10", "optional": true},
      "temperature": {"column": "temp", "optional": true},
      "timestamp": {"column": "Timestamp", "format": "%Y%m%d%H%M%S", "optional": true},
      "point_offset_m": 0.1
    }

Only ``measured`` is required. ``euler`` uses SciPy's notation: upper case is
intrinsic (rotating axes), lower case extrinsic (fixed axes). A group may be a list of
alternatives; the first whose columns are all in the file is used. A group marked
``"optional": true`` is skipped when its columns are absent, any other missing column
is an error.

Representation (docs/import.md): each measured pose becomes 4 virtual points, the
probe origin and the origin + `point_offset_m` along the probe's x, y, z axes, as LEDs
1..4 of ``/tracker/positions`` (camera = tracker frame); the tool constellation is those
4 points in the probe frame with reference LEDs 1, 2, 3; the measured pose itself is
also stored as ``/probe``; joint angles go to ``/robot/joints``, commanded flange poses
to ``/program/targets``, temperature to ``/tracker/temperature`` and the tracker's
standard deviations to ``/tracker/pose_std``.
"""

from __future__ import annotations

import copy
import datetime
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from .._errors import UserError
from ..recording import Pose, Probe, Program, Recording, RecordingError, RobotLog, Tool
from ._common import UR_JOINTS, quat_wxyz

# christianlandgraf/ipa-robot-accuracy (UR10 + Leica laser tracker with T-Mac probe).
# The measured Euler convention (intrinsic XYZ, degrees) is the one the publication's
# reader uses; tests/importers verify it against the rigid-fit residual.
PRESETS: dict[str, dict[str, Any]] = {
    "ipa-ur10": {
        "delimiter": ";",
        "decimal": ",",
        "measured": {
            "position": ["measurement_x", "measurement_y", "measurement_z"],
            "position_unit": "mm",
            "rotation": ["measurement_rx", "measurement_ry", "measurement_rz"],
            "angle_unit": "deg",
            "euler": "XYZ",
        },
        "measured_std": {
            "position": ["measurement_std_x", "measurement_std_y", "measurement_std_z"],
            "rotation": ["measurement_std_rx", "measurement_std_ry", "measurement_std_rz"],
            "optional": True,
        },
        "commanded": [
            {
                "position": ["Goal x", "Goal y", "Goal z"],
                "position_unit": "m",
                "rotation": ["Goal roll", "Goal pitch", "Goal yaw"],
                "angle_unit": "rad",
                "euler": "xyz",
                "optional": True,
            },
            {
                "position": ["flange_x", "flange_y", "flange_z"],
                "position_unit": "m",
                "quaternion_xyzw": ["flange_qx", "flange_qy", "flange_qz", "flange_qw"],
                "optional": True,
            },
        ],
        "joints": {
            "columns": list(UR_JOINTS),
            "angle_unit": "rad",
            "model": "ur10",
            "optional": True,
        },
        "temperature": {"column": "measurement_temperature", "optional": True},
        "timestamp": {"column": "Timestamp", "format": "%Y%m%d%H%M%S", "optional": True},
        "point_offset_m": 0.1,
    }
}

_LENGTH = {"m": 1.0, "mm": 1e-3}
_ANGLE = {"rad": 1.0, "deg": np.pi / 180}


def load_mapping(
    preset: str | None = None,
    mapping: str | os.PathLike | Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """A mapping from a preset name, updated by a JSON file (or dict) on top of it."""
    if preset is not None and preset not in PRESETS:
        raise UserError(f"unknown preset {preset!r} (known: {', '.join(sorted(PRESETS))})")
    out: dict[str, Any] = copy.deepcopy(PRESETS[preset]) if preset else {}
    if mapping is not None:
        if isinstance(mapping, Mapping):
            doc = dict(mapping)
        else:
            try:
                doc = json.loads(Path(mapping).read_text())
            except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
                raise UserError(f"{mapping}: not a readable JSON mapping ({e})") from None
            if not isinstance(doc, dict):
                raise UserError(f"{mapping}: a mapping file holds one JSON object")
        out.update(copy.deepcopy(doc))
    if "measured" not in out:
        raise UserError(
            "pose-csv needs a column mapping: --preset NAME, --mapping FILE or --position-cols "
            "and --rotation-cols"
        )
    return out


class _Table:
    def __init__(self, path: Path, delimiter: str, decimal: str) -> None:
        self.path = path
        try:
            lines = [ln for ln in path.read_text(encoding="utf-8-sig").splitlines() if ln.strip()]
        except (OSError, UnicodeDecodeError) as e:
            raise UserError(f"{path}: cannot read as text ({e})") from None
        if len(lines) < 2:
            raise RecordingError(f"{path}: needs a header row and at least one data row")
        self.header = [h.strip() for h in lines[0].split(delimiter)]
        self.rows = [[c.strip() for c in ln.split(delimiter)] for ln in lines[1:]]
        for i, row in enumerate(self.rows):
            if len(row) != len(self.header):
                raise RecordingError(
                    f"{path}: row {i + 2} has {len(row)} fields, the header has "
                    f"{len(self.header)} (delimiter {delimiter!r})"
                )
        self.decimal = decimal
        self.index = {h: i for i, h in enumerate(self.header)}

    def has(self, cols: list[str]) -> bool:
        return all(c in self.index for c in cols)

    def text(self, col: str) -> list[str]:
        return [row[self.index[col]] for row in self.rows]

    def numbers(self, cols: list[str]) -> np.ndarray:
        missing = [c for c in cols if c not in self.index]
        if missing:
            raise UserError(f"{self.path}: no column {missing[0]!r} (columns: {self.header})")
        out = np.empty((len(self.rows), len(cols)))
        for j, col in enumerate(cols):
            k = self.index[col]
            for i, row in enumerate(self.rows):
                cell = row[k]
                if self.decimal != ".":
                    cell = cell.replace(self.decimal, ".")
                try:
                    out[i, j] = float(cell) if cell else np.nan
                except ValueError:
                    raise RecordingError(
                        f"{self.path}: row {i + 2}, column {col!r}: {row[k]!r} is not a number"
                    ) from None
        return out


def _pick(table: _Table, spec: Any, name: str) -> dict[str, Any] | None:
    """The alternative of group `spec` whose columns the table has (None: optional, absent)."""
    if spec is None:
        return None
    alternatives = spec if isinstance(spec, list) else [spec]
    for alt in alternatives:
        if table.has(_columns(alt)):
            return alt
    if all(alt.get("optional", False) for alt in alternatives):
        return None
    want = [c for c in _columns(alternatives[0]) if c not in table.index]
    raise UserError(f"{table.path}: {name} column {want[0]!r} not found (columns: {table.header})")


def _columns(alt: Mapping[str, Any]) -> list[str]:
    cols = []
    for key in ("position", "rotation", "quaternion_xyzw", "columns"):
        cols += list(alt.get(key, []))
    if "column" in alt:
        cols.append(alt["column"])
    return cols


def _unit(table: dict[str, float], unit: str, what: str) -> float:
    if unit not in table:
        raise UserError(f"{what} unit {unit!r} is not one of {', '.join(table)}")
    return table[unit]


def _pose(table: _Table, spec: Mapping[str, Any], name: str) -> tuple[np.ndarray, Rotation]:
    if len(spec.get("position", [])) != 3:
        raise UserError(f"mapping: {name}.position must name 3 columns")
    pos = table.numbers(list(spec["position"])) * _unit(
        _LENGTH, spec.get("position_unit", "m"), f"{name} position"
    )
    if "quaternion_xyzw" in spec:
        q = table.numbers(list(spec["quaternion_xyzw"]))
        bad = ~np.all(np.isfinite(q), axis=1) | (np.linalg.norm(q, axis=1) < 0.5)
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise RecordingError(f"{table.path}: row {i + 2}: {name} quaternion is not a rotation")
        return pos, Rotation.from_quat(q)
    if len(spec.get("rotation", [])) != 3:
        raise UserError(f"mapping: {name} needs 3 'rotation' columns or 4 'quaternion_xyzw'")
    euler = str(spec.get("euler", ""))
    if (
        len(euler) != 3
        or not (euler.isupper() or euler.islower())
        or set(euler.lower())
        - {
            "x",
            "y",
            "z",
        }
    ):
        raise UserError(
            f"mapping: {name}.euler {euler!r} is not an Euler sequence such as 'XYZ' "
            "(intrinsic) or 'xyz' (extrinsic)"
        )
    ang = table.numbers(list(spec["rotation"])) * _unit(
        _ANGLE, spec.get("angle_unit", "rad"), f"{name} angle"
    )
    if not np.all(np.isfinite(ang)):
        i = int(np.flatnonzero(~np.all(np.isfinite(ang), axis=1))[0])
        raise RecordingError(f"{table.path}: row {i + 2}: {name} rotation is missing")
    return pos, Rotation.from_euler(euler, ang)


def _matrices(pos: np.ndarray, rot: Rotation) -> np.ndarray:
    T = np.tile(np.eye(4), (pos.shape[0], 1, 1))
    T[:, :3, :3] = rot.as_matrix()
    T[:, :3, 3] = pos
    return T


def _timestamps(table: _Table, spec: Mapping[str, Any] | None) -> np.ndarray | None:
    """POSIX seconds (the clock's own zone read as UTC) or None when not parseable."""
    if spec is None:
        return None
    fmt = spec.get("format", "%Y%m%d%H%M%S")
    out = []
    for cell in table.text(spec["column"]):
        try:
            t = datetime.datetime.strptime(cell, fmt).replace(tzinfo=datetime.UTC)
        except ValueError:
            return None  # e.g. rounded by a spreadsheet: not usable
        out.append(t.timestamp())
    return np.asarray(out, np.float64)


def _read(path: Path, mapping: Mapping[str, Any]) -> dict[str, Any]:
    table = _Table(path, str(mapping.get("delimiter", ",")), str(mapping.get("decimal", ".")))
    measured = _pick(table, mapping["measured"], "measured")
    pos, rot = _pose(table, measured, "measured")
    if not np.all(np.isfinite(pos)):
        i = int(np.flatnonzero(~np.all(np.isfinite(pos), axis=1))[0])
        raise RecordingError(f"{path}: row {i + 2}: measured position is missing")
    out: dict[str, Any] = {"table": table, "measured": _matrices(pos, rot), "rot": rot}
    out["euler"] = measured.get("euler", "quaternion")
    std_spec = _pick(table, mapping.get("measured_std"), "measured_std")
    out["std"] = None
    if std_spec is not None:
        p = table.numbers(list(std_spec["position"])) * _unit(
            _LENGTH, measured.get("position_unit", "m"), "std position"
        )
        r = table.numbers(list(std_spec["rotation"])) * _unit(
            _ANGLE, measured.get("angle_unit", "rad"), "std angle"
        )
        out["std"] = np.concatenate([p, r], axis=1)
    cmd = _pick(table, mapping.get("commanded"), "commanded")
    out["commanded"] = None if cmd is None else _matrices(*_pose(table, cmd, "commanded"))
    joints = _pick(table, mapping.get("joints"), "joints")
    out["joints"] = None
    out["model"] = None
    if joints is not None:
        q = table.numbers(list(joints["columns"]))
        out["joints"] = q * _unit(_ANGLE, joints.get("angle_unit", "rad"), "joint angle")
        out["model"] = joints.get("model")
    temp = _pick(table, mapping.get("temperature"), "temperature")
    out["temperature"] = None if temp is None else table.numbers([temp["column"]])[:, 0]
    out["timestamp"] = _timestamps(table, _pick(table, mapping.get("timestamp"), "timestamp"))
    return out


def load_pose_series(
    path: str | os.PathLike,
    preset: str | None = "ipa-ur10",
    mapping: str | os.PathLike | Mapping[str, Any] | None = None,
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """One pose-CSV series as plain arrays, for notebooks.

    Returns ``(joints, measured, commanded, temperature, std)``: joint angles `(N, J)`
    [rad]; measured probe poses in the tracker frame as `(N, 4, 4)` matrices [m];
    commanded flange poses in the base frame `(N, 4, 4)` [m]; temperature `(N,)` [°C];
    tracker standard deviations `(N, 6)` (x, y, z [m], rx, ry, rz [rad]). Absent
    columns give None.
    """
    d = _read(Path(path), load_mapping(preset, mapping))
    return d["joints"], d["measured"], d["commanded"], d["temperature"], d["std"]


def import_pose_csv(
    path: str | os.PathLike,
    *,
    preset: str | None = None,
    mapping: str | os.PathLike | Mapping[str, Any] | None = None,
    rate: float | None = None,
) -> Recording:
    """Import a 6-DOF pose CSV as a schema-1 `Recording` (representation: module docstring).

    Pose ``i`` is at ``time = i / rate`` (default 1 Hz: static poses, one per second);
    usable wall-clock timestamps are kept in ``/tracker/wallclock`` [s, POSIX].
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    m = load_mapping(preset, mapping)
    d = _read(path, m)
    hz = 1.0 if rate is None else float(rate)
    if not np.isfinite(hz) or hz <= 0:
        raise UserError(f"--rate must be a positive frequency, got {rate!r}")
    offset = float(m.get("point_offset_m", 0.1))
    if not offset > 0:
        raise UserError(f"mapping: point_offset_m must be positive, got {offset!r}")
    measured = d["measured"]
    n = measured.shape[0]
    points = np.vstack([np.zeros(3), offset * np.eye(3)])  # (4, 3) in the probe frame
    positions = measured[:, None, :3, 3] + np.einsum("nij,kj->nki", measured[:, :3, :3], points)
    time = np.arange(n, dtype=np.float64) / hz
    led_ids = np.arange(1, 5, dtype=np.int32)
    tool = Tool(led_ids=led_ids, constellation=points, reference_leds=np.array([1, 2, 3], np.int32))
    probe = Probe(
        time=time, tool_pose=Pose(position=measured[:, :3, 3], quaternion_wxyz=quat_wxyz(d["rot"]))
    )
    robot = None
    extra_attrs: dict[str, dict[str, Any]] = {}
    if d["joints"] is not None:
        robot = RobotLog(time=time.copy(), joints=d["joints"], model=d["model"])
    program = None
    if d["commanded"] is not None:
        cmd = d["commanded"]
        program = Program(
            targets=Pose(
                position=cmd[:, :3, 3],
                quaternion_wxyz=quat_wxyz(Rotation.from_matrix(cmd[:, :3, :3])),
            ),
            motion=np.full(n, "joint"),
            speed=np.zeros(n),
        )
    extras: dict[str, np.ndarray] = {}
    if d["std"] is not None:
        extras["tracker/pose_std"] = d["std"]
        extra_attrs["tracker/pose_std"] = {
            "description": "tracker standard deviation of the measured probe pose per frame",
            "columns": "x, y, z [m], rx, ry, rz [rad] (of the measured Euler angles)",
        }
    if d["timestamp"] is not None:
        extras["tracker/wallclock"] = d["timestamp"]
        extra_attrs["tracker/wallclock"] = {
            "description": "wall-clock time of each measurement, POSIX seconds (local time "
            "read as UTC); not guaranteed monotonic"
        }
    attrs = {
        "source": "import",
        "import_format": "pose-csv",
        "import_file": path.name,
        "import_preset": preset or "",
        "import_euler": d["euler"],
        "import_representation": (
            f"4 virtual points per measured pose: probe origin and origin + {offset} m along "
            "the probe x, y, z axes (LEDs 1..4)"
        ),
    }
    return Recording(
        time=time,
        frame_index=np.arange(n, dtype=np.uint64),
        led_ids=led_ids,
        positions=positions,
        status=np.zeros((n, 4), np.uint8),
        temperature=None if d["temperature"] is None else d["temperature"].astype(np.float32),
        robot=robot,
        program=program,
        tool=tool,
        probe=probe,
        attrs=attrs,
        extras=extras,
        extra_attrs=extra_attrs,
    )


def import_pose_folder(
    folder: str | os.PathLike,
    *,
    preset: str | None = "ipa-ur10",
    mapping: str | os.PathLike | Mapping[str, Any] | None = None,
    rate: float | None = None,
) -> dict[str, Recording]:
    """Import every ``*.csv`` under `folder` (recursively) that the mapping fits.

    Keys are the CSV paths relative to `folder` (``"Series_A/measurements_grid.csv"``).
    """
    folder = Path(folder)
    files = sorted(folder.rglob("*.csv"))
    if not files:
        raise UserError(f"{folder}: no .csv files in this folder")
    return {
        f.relative_to(folder).as_posix(): import_pose_csv(
            f, preset=preset, mapping=mapping, rate=rate
        )
        for f in files
    }
