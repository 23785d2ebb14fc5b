"""Shared pieces of the importers: tool constellations, rotations, attributes."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from .._errors import UserError
from ..recording import Pose, Tool

# NDI Optotrak 6-marker probe of the kineticstoolkit recordings (README of
# data/optotrak-n3d-probe): tool frame origin at the probe tip, metres, markers 0-5.
OPTOTRAK_PROBE = Tool(
    led_ids=np.arange(6, dtype=np.int32),
    constellation=np.array(
        [
            [0.0021213, -0.0158328, 0.0864285],
            [0.0021213, 0.0158508, 0.0864285],
            [0.0020575, 0.0160096, 0.1309445],
            [0.0021213, 0.0161204, 0.1754395],
            [0.0017070, -0.0155780, 0.1753805],
            [0.0017762, -0.0156057, 0.1308888],
        ]
    ),
    reference_leds=np.array([0, 1, 3], dtype=np.int32),
)

BUILTIN_CONSTELLATIONS: dict[str, Tool] = {"optotrak-probe": OPTOTRAK_PROBE}

#: Universal Robots' joint names (URDF, RTDE and ROS driver), base to wrist
UR_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)


def load_constellation(source: str | os.PathLike | Tool) -> Tool:
    """A tool (LED constellation) from a built-in name, a JSON file or a CSV file.

    JSON: ``{"led_ids": [..], "positions": [[x, y, z], ..], "unit": "m"|"mm",
    "reference_leds": [a, b, c], "normals": [[nx, ny, nz], ..],
    "flange_from_tool": {"position": [x, y, z], "quaternion_wxyz": [w, x, y, z]}}``, all
    in the tool frame (``unit`` defaults to ``"m"`` and also scales the flange←tool
    position; ``reference_leds``, ``normals`` (LED emission axes, normalised on
    reading) and ``flange_from_tool`` (the nominal TCP) are optional); a robtraj
    ``CALIB.json`` (its ``"constellation"`` member) works too.
    CSV: one row per LED ``id, x, y, z`` in metres, optionally ``, nx, ny, nz``, an
    optional header row; a header naming ``mm`` (e.g. ``id,x_mm,y_mm,z_mm``) means
    millimetres.
    """
    if isinstance(source, Tool):
        return source
    if str(source) in BUILTIN_CONSTELLATIONS:
        return BUILTIN_CONSTELLATIONS[str(source)]
    path = Path(source)
    if not path.is_file():
        names = ", ".join(sorted(BUILTIN_CONSTELLATIONS))
        raise UserError(f"{path}: no such constellation file (built-in constellations: {names})")
    if path.suffix.lower() == ".json":
        return _constellation_json(path)
    return _constellation_csv(path)


def _constellation_json(path: Path) -> Tool:
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise UserError(f"{path}: not a readable JSON constellation ({e})") from None
    if isinstance(doc, dict) and isinstance(doc.get("constellation"), dict):
        doc = doc["constellation"]
    if not isinstance(doc, dict) or "led_ids" not in doc or "positions" not in doc:
        raise UserError(f"{path}: a constellation needs 'led_ids' and 'positions'")
    scale = _unit_scale(str(doc.get("unit", "m")), path)
    ref = doc.get("reference_leds")
    tool = _make_tool(doc["led_ids"], doc["positions"], scale, ref, path)
    normals = None if doc.get("normals") is None else _normals(doc["normals"], tool, path)
    fft = None
    if doc.get("flange_from_tool") is not None:
        fft = _pose_member(doc["flange_from_tool"], scale, path, "flange_from_tool")
    return dataclasses.replace(tool, normals=normals, flange_from_tool=fft)


def _normals(values, tool: Tool, path: Path) -> np.ndarray:
    try:
        n = np.asarray(values, np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{path}: normals are not numeric") from None
    norm = np.linalg.norm(n, axis=-1, keepdims=True) if n.ndim == 2 else None
    if n.shape != tool.constellation.shape or not np.all(np.isfinite(n)) or np.any(norm == 0):
        raise UserError(f"{path}: normals must be one finite, non-zero 3-vector per LED")
    return n / norm


def _pose_member(doc, scale: float, path: Path, name: str) -> Pose:
    try:
        position = np.asarray(doc["position"], np.float64) * scale
        q = np.asarray(doc["quaternion_wxyz"], np.float64)
    except (TypeError, KeyError, ValueError):
        raise UserError(
            f"{path}: {name} needs 'position' [x, y, z] and 'quaternion_wxyz'"
        ) from None
    if position.shape != (3,) or q.shape != (4,) or not np.all(np.isfinite([*position, *q])):
        raise UserError(f"{path}: {name} needs 3 finite coordinates and a 4-element quaternion")
    if abs(np.linalg.norm(q) - 1.0) > 1e-6:
        raise UserError(f"{path}: {name}.quaternion_wxyz is not a unit quaternion")
    return Pose(position, q / np.linalg.norm(q))


def tool_document(tool: Tool) -> dict:
    """`tool` as the JSON document `load_constellation` reads (metres)."""
    doc: dict = {
        "unit": "m",
        "led_ids": np.asarray(tool.led_ids).tolist(),
        "positions": np.asarray(tool.constellation).tolist(),
    }
    if tool.reference_leds is not None:
        doc["reference_leds"] = np.asarray(tool.reference_leds).tolist()
    if tool.normals is not None:
        doc["normals"] = np.asarray(tool.normals).tolist()
    if tool.flange_from_tool is not None:
        doc["flange_from_tool"] = {
            "position": np.asarray(tool.flange_from_tool.position).tolist(),
            "quaternion_wxyz": np.asarray(tool.flange_from_tool.quaternion_wxyz).tolist(),
        }
    return doc


def _constellation_csv(path: Path) -> Tool:
    try:
        rows = [r for r in csv.reader(path.read_text().splitlines()) if r and any(r)]
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: not a readable CSV constellation ({e})") from None
    scale = 1.0
    if rows and not _is_number(rows[0][0]):
        scale = 1e-3 if "mm" in ",".join(rows[0]).lower() else 1.0
        rows = rows[1:]
    try:
        ids = [int(r[0]) for r in rows]
        pos = [[float(v) for v in r[1:4]] for r in rows]
        normals = [[float(v) for v in r[4:7]] for r in rows if len(r) >= 7]
    except (ValueError, IndexError):
        raise UserError(
            f"{path}: each constellation row must be 'id, x, y, z' or 'id, x, y, z, nx, ny, nz'"
        ) from None
    tool = _make_tool(ids, pos, scale, None, path)
    if not normals:
        return tool
    if len(normals) != len(ids):
        raise UserError(f"{path}: either every row or none has a normal 'nx, ny, nz'")
    return dataclasses.replace(tool, normals=_normals(normals, tool, path))


def _make_tool(ids, positions, scale: float, ref, path: Path) -> Tool:
    try:
        led_ids = np.asarray(ids, dtype=np.int32)
        pos = np.asarray(positions, dtype=np.float64) * scale
    except (TypeError, ValueError):
        raise UserError(f"{path}: constellation led_ids/positions are not numeric") from None
    if led_ids.ndim != 1 or pos.shape != (led_ids.shape[0], 3) or led_ids.shape[0] < 3:
        raise UserError(
            f"{path}: constellation needs at least 3 LEDs with 3 coordinates each "
            f"(got ids {led_ids.shape}, positions {pos.shape})"
        )
    if len(set(led_ids.tolist())) != led_ids.shape[0] or not np.all(np.isfinite(pos)):
        raise UserError(f"{path}: constellation LED ids must be unique and positions finite")
    reference = None
    if ref is not None:
        reference = np.asarray(ref, dtype=np.int32)
        if reference.shape != (3,) or not np.all(np.isin(reference, led_ids)):
            raise UserError(f"{path}: reference_leds must be three of the constellation's ids")
    return Tool(led_ids=led_ids, constellation=pos, reference_leds=reference)


def _unit_scale(unit: str, where: object) -> float:
    scales = {"m": 1.0, "mm": 1e-3}
    if unit not in scales:
        raise UserError(f"{where}: length unit {unit!r} is not one of m, mm")
    return scales[unit]


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def quat_wxyz(rot: Rotation) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` in w, x, y, z order, w >= 0."""
    q = np.asarray(rot.as_quat(), np.float64)
    q = np.concatenate([q[..., 3:], q[..., :3]], axis=-1)
    q = np.where(q[..., :1] < 0, -q, q)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)
