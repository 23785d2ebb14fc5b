"""A simulated recording split into the files a lab has after a measurement campaign.

The tracker stream alone (what `robtraj record` writes), the controller's joint log on
its own clock (another epoch and an offset of seconds), the robot as URDF, the tool as
JSON and the program as CSV: the inputs of `robtraj attach`.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from ..importers import program_csv, tool_document
from ..model import BUILTIN_ROBOTS, urdf_text
from ..recording import Recording, write_recording

#: [s] UNIX time of the simulated controller clock's zero (2026-05-28 02:13:20 UTC)
CONTROLLER_EPOCH = 1.78e9


@dataclasses.dataclass(frozen=True)
class CampaignFiles:
    """Paths of a campaign's parts and the robot clock's true offset [s] (robot −
    tracker, including the simulated τ)."""

    tracker: Path
    robot_log: Path
    mapping: Path | None
    robot: Path
    tool: Path
    program: Path
    clock_offset: float


def write_campaign(
    rec: Recording,
    folder: str | Path,
    *,
    name: str = "run",
    clock_offset: float = 7.3,
    log_format: str = "csv",
) -> CampaignFiles:
    """Write `rec`'s parts into `folder` (which must exist): ``{name}_tracker.h5``, the
    joint log ``{name}_joints.csv`` (``log_format`` ``"csv"``: semicolons, decimal
    commas, degrees and milliseconds of UNIX time with ``{name}_joints.mapping.json``;
    ``"ur-rtde"``: a UR RTDE CSV in radians and seconds), ``robot.urdf``, ``tool.json``
    and ``{name}_program.csv``. The log's clock is `CONTROLLER_EPOCH` + `clock_offset`
    ahead of the tracker's; the simulation's own τ comes on top."""
    folder = Path(folder)
    tracker = rec.replace(robot=None, tool=None, program=None, truth=None)
    paths = {
        "tracker": write_recording(tracker, folder / f"{name}_tracker.h5"),
        "robot": folder / "robot.urdf",
        "tool": folder / "tool.json",
        "program": folder / f"{name}_program.csv",
    }
    robot = BUILTIN_ROBOTS[rec.robot.model]()
    paths["robot"].write_text(urdf_text(robot))
    paths["tool"].write_text(json.dumps(tool_document(rec.tool), indent=1))
    paths["program"].write_text(program_csv(rec.program))
    offset = CONTROLLER_EPOCH + clock_offset
    log_path = folder / f"{name}_joints.csv"
    mapping = None
    if log_format == "csv":
        mapping = folder / f"{name}_joints.mapping.json"
        _write_generic_log(log_path, mapping, rec.robot.time + offset, rec.robot.joints)
    elif log_format == "ur-rtde":
        _write_rtde_log(log_path, rec.robot.time + offset, rec.robot.joints)
    else:
        raise ValueError(f"unknown log format {log_format!r}")
    truth_tau = float((rec.truth.effects if rec.truth else {}).get("time_offset", 0.0) or 0.0)
    return CampaignFiles(
        tracker=paths["tracker"], robot_log=log_path, mapping=mapping, robot=paths["robot"],
        tool=paths["tool"], program=paths["program"], clock_offset=offset + truth_tau,
    )  # fmt: skip


def _write_generic_log(path: Path, mapping: Path, time: np.ndarray, joints: np.ndarray) -> None:
    names = [f"A{j + 1}" for j in range(joints.shape[1])]
    rows = [";".join(["time_ms", *names])]
    for t, q in zip(time * 1e3, np.rad2deg(joints), strict=True):
        rows.append(";".join([f"{t:.3f}", *(f"{v:.9f}" for v in q)]).replace(".", ","))
    path.write_text("\n".join(rows) + "\n")
    mapping.write_text(
        json.dumps(
            {
                "time": "time_ms",
                "time_unit": "ms",
                "joints": names,
                "unit": "deg",
                "delimiter": ";",
                "decimal": ",",
            },
            indent=1,
        )  # fmt: skip
    )


def _write_rtde_log(path: Path, time: np.ndarray, joints: np.ndarray) -> None:
    j = joints.shape[1]
    head = ["timestamp", *(f"target_q_{k}" for k in range(j)), *(f"actual_q_{k}" for k in range(j))]
    rows = [" ".join(head)]
    for t, q in zip(time, joints, strict=True):
        rows.append(" ".join([f"{t:.6f}", *(f"{v:.12f}" for v in q), *(f"{v:.12f}" for v in q)]))
    path.write_text("\n".join(rows) + "\n")
