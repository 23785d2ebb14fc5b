"""The tool poses a recording's report shows: in the robot base frame when the recording
could be put there, else fitted in the camera frame, else none."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .._errors import UserError


@dataclasses.dataclass(frozen=True)
class ToolPoses:
    """The frame of the poses in words (`frame`), the `PoseEstimate` (`estimate`, None
    when there are no poses) with its `time` [s] `(frames,)` and the tool `position` [m]
    `(frames, 3)` in that frame; `warnings` say why there are none."""

    frame: str
    estimate: Any = None
    time: np.ndarray | None = None
    position: np.ndarray | None = None
    warnings: tuple[str, ...] = ()


def tool_poses(rec, base_poses) -> ToolPoses:
    """`base_poses` (from `robtraj.estimate._base_frame.base_frame_poses`) when given;
    else the poses fitted in the camera frame when the recording has a tool."""
    from ..estimate import estimate_poses

    if base_poses is not None:
        return ToolPoses("robot base frame", base_poses.poses, base_poses.time, base_poses.position)
    if rec.tool is None:
        return ToolPoses(
            "none: the recording has no tool constellation",
            warnings=("no tool constellation: only the LED data are reported",),
        )
    try:
        est = estimate_poses(rec)
    except UserError as e:
        return ToolPoses(
            "none: the tool poses could not be fitted", warnings=(f"tool poses left out: {e}",)
        )
    return ToolPoses(
        "camera (tracker) frame, no calibration to the robot base", est, est.time, est.position
    )
