"""The measured tool path in a recording's report: its deviation from the commanded path,
the TCP speed and the quality of the per-frame pose fit."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._figures import deviation_figure, path_3d_figure, pose_quality_figure, velocity_figure
from ._html import Figure, Section, Table
from ._report_part import ReportPart, left_out
from ._tool_poses import ToolPoses
from ._words import column_label


def deviation_part(out: Path, deviation, reference, position) -> ReportPart:
    """The section of a `DeviationResult` (figures `out/path_3d.png` and
    `out/deviation.png` of the measured TCP `position` [m] `(frames, 3)` and the
    `ReferencePath` `reference`) and its summary line; left out without one."""
    if deviation is None:
        return left_out(
            "Path deviation",
            "needs a program with linear moves and base-frame poses; see the notes in the summary.",
        )
    s = deviation.summary()
    fact = (
        "path deviation",
        f"RMS {s.distance_rms * 1e3:.3f} mm, max {s.distance_max * 1e3:.3f} mm; "
        f"orientation RMS {np.degrees(s.orientation_rms):.4f}° over {s.n} frames "
        "on linear moves",
    )
    figs = [
        Figure(
            path_3d_figure(
                out / "path_3d.png",
                position,
                deviation.distance,
                reference=None if reference is None else reference.position,
            ),
            "Measured TCP path (points coloured by their distance to the commanded path) "
            "and the commanded path (red, dashed, drawn on top); left in 3D, right seen "
            "from above.",
        ),
        Figure(
            deviation_figure(
                out / "deviation.png",
                deviation.progress,
                deviation.distance,
                deviation.orientation_error,
                on_path=deviation.on_path,
            ),
            "Distance to the commanded path and orientation error against path "
            "progress; grey: frames on joint moves, where the path is not specified.",
        ),
    ]
    sj = s.to_json()
    section = Section(
        "Path deviation",
        "Point-to-segment distance to the commanded path (match monotone in path "
        "progress) and the single-angle orientation error at the foot point.",
        figures=figs,
        tables=[
            Table(
                "Deviation summary",
                ["quantity", "value"],
                [[column_label(k), v] for k, v in sj.items()],
                "Over the seen frames on linear moves.",
            )
        ],
    )
    return ReportPart(section, (fact,))


def speed_part(out: Path, poses: ToolPoses) -> ReportPart:
    """The speed of the measured tool point (figure `out/speed.png`); nothing without
    poses."""
    if poses.estimate is None:
        return ReportPart()
    t, position = poses.time, poses.position
    speed = _speed(t, position)
    return ReportPart(
        Section(
            "TCP speed",
            figures=[
                Figure(
                    velocity_figure(out / "speed.png", t, speed),
                    f"Speed of the measured tool point ({poses.frame}), central differences "
                    "between frames.",
                )
            ],
        )
    )


def pose_quality_part(out: Path, poses: ToolPoses) -> ReportPart:
    """The per-frame residual RMS of the pose fit and the LEDs it used (figure
    `out/pose_quality.png`); nothing without poses."""
    est = poses.estimate
    if est is None:
        return ReportPart()
    return ReportPart(
        Section(
            "Pose quality",
            figures=[
                Figure(
                    pose_quality_figure(out / "pose_quality.png", poses.time, est.rms, est.n_used),
                    f"Per-frame weighted residual RMS of the tool pose fit ({est.weighting} "
                    "weighting) and the number of LEDs it used.",
                )
            ],
        )
    )


def _speed(t: np.ndarray, position: np.ndarray, block: int = 1 << 16) -> np.ndarray:
    """|d position / dt| `(N,)` [m/s] by `np.gradient` (central differences, one-sided
    at the ends), `block` frames at a time with one frame either side."""
    n = t.shape[0]
    if n < 2:
        return t * 0
    speed = np.empty(n)
    for a in range(0, n, block):
        lo, hi = max(a - 1, 0), min(a + block + 1, n)
        v = np.gradient(position[lo:hi], t[lo:hi], axis=0)[a - lo : a - lo + block]
        speed[a : a + v.shape[0]] = np.linalg.norm(v, axis=1)
    return speed
