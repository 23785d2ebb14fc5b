"""Import real data from other trackers into schema-1 recordings (docs/import.md).

- `import_n3d`: NDI Optotrak N3D marker files.
- `import_pose_csv`: 6-DOF pose measurements in CSV (laser tracker with a 6-DOF probe),
  with presets such as ``"ipa-ur10"``; `load_pose_series` gives the same data as plain
  arrays for notebooks.
- `import_file`: pick the importer from `format` or the file name.

NatNet captures (``--format natnet``) are decoded by `acquisition.natnet`; the
``robtraj import`` command reaches them from the CLI layer.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from .._errors import UserError
from ..recording import Recording
from ._attach import Parts as Parts, attach as attach, read_parts as read_parts
from ._common import (
    BUILTIN_CONSTELLATIONS as BUILTIN_CONSTELLATIONS,
    load_constellation,
    tool_document as tool_document,
)
from ._n3d import import_n3d as import_n3d, read_n3d as read_n3d
from ._pose_csv import (
    PRESETS as PRESETS,
    import_pose_csv as import_pose_csv,
    import_pose_folder as import_pose_folder,
    load_mapping as load_mapping,
    load_pose_series as load_pose_series,
)
from ._program import program_csv as program_csv, read_program as read_program
from ._robot_log import (
    JOINT_LOG_FORMATS as JOINT_LOG_FORMATS,
    JointLog as JointLog,
    read_joint_log as read_joint_log,
)
from ._robot_model import (
    RobotDescription as RobotDescription,
    read_robot_model as read_robot_model,
    robot_description as robot_description,
    write_robot_model as write_robot_model,
)

__all__ = [
    "Parts",
    "attach",
    "read_parts",
    "robot_description",
    "program_csv",
    "read_program",
    "tool_document",
    "BUILTIN_CONSTELLATIONS",
    "PRESETS",
    "RobotDescription",
    "FORMATS",
    "JOINT_LOG_FORMATS",
    "JointLog",
    "guess_format",
    "import_file",
    "import_n3d",
    "import_pose_csv",
    "import_pose_folder",
    "load_constellation",
    "load_mapping",
    "load_pose_series",
    "read_joint_log",
    "read_n3d",
    "read_robot_model",
    "write_robot_model",
]

FORMATS = ("n3d", "pose-csv", "natnet")
_EXTENSIONS = {".n3d": "n3d", ".csv": "pose-csv", ".txt": "pose-csv", ".bin": "natnet"}


def guess_format(src: str | os.PathLike) -> str:
    """The format named by `src`'s extension (a folder: ``pose-csv``); `UserError` if unknown."""
    path = Path(src)
    if path.is_dir():
        return "pose-csv"
    fmt = _EXTENSIONS.get(path.suffix.lower())
    if fmt is None:
        raise UserError(
            f"{path}: cannot tell the format from the extension {path.suffix!r}; "
            f"give --format ({', '.join(FORMATS)})"
        )
    return fmt


def import_file(src: str | os.PathLike, format: str | None = None, **opts: Any) -> Recording:
    """Import one file with the importer for `format` (guessed from the extension if None).

    `opts` go to the importer: ``constellation``, ``rate`` (n3d); ``preset``, ``mapping``,
    ``rate`` (pose-csv). A ``preset`` naming a built-in constellation (``optotrak-probe``)
    is accepted for n3d as the constellation.
    """
    path = Path(src)
    if not path.exists():
        raise UserError(f"{path}: no such file")
    fmt = format or guess_format(path)
    if fmt == "n3d":
        preset = opts.pop("preset", None)
        if preset is not None:
            if preset not in BUILTIN_CONSTELLATIONS:
                names = ", ".join(sorted(BUILTIN_CONSTELLATIONS))
                raise UserError(f"unknown n3d preset {preset!r} (known: {names})")
            if opts.get("constellation") is None:
                opts["constellation"] = preset
        _only(opts, {"constellation", "rate"}, fmt)
        return import_n3d(path, **opts)
    if fmt == "pose-csv":
        _only(opts, {"preset", "mapping", "rate"}, fmt)
        return import_pose_csv(path, **opts)
    if fmt == "natnet":
        raise UserError("natnet captures are imported by acquisition.natnet.import_natnet")
    raise UserError(f"unknown format {fmt!r} (known: {', '.join(FORMATS)})")


def _only(opts: dict[str, Any], allowed: set[str], fmt: str) -> None:
    given = {k for k, v in opts.items() if v is not None}
    extra = sorted(given - allowed)
    if extra:
        raise UserError(f"--{extra[0]} does not apply to format {fmt}")
    for k in list(opts):
        if opts[k] is None:
            del opts[k]
