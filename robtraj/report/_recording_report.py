"""The test report of one recording: summary, calibration, ISO 9283 tables, path deviation,
speed, LEDs and pose quality. Sections whose inputs are absent are left out with a note."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ._calibration_section import calibration_part
from ._compensation_section import compensation_part
from ._html import Section, Summary, write_report
from ._iso_section import iso_part
from ._led_sections import led_part, noise_part
from ._path_sections import deviation_part, pose_quality_part, speed_part
from ._report_part import ReportPart
from ._static_pose_section import static_pose_part
from ._tool_poses import ToolPoses, tool_poses


def recording_report(
    out_dir: str | os.PathLike,
    rec,
    calibration=None,
    base_poses=None,
    *,
    deviation=None,
    reference=None,
    iso=None,
    extra_sections: tuple[Section, ...] = (),
    name: str = "recording",
    notes: Sequence[str] = (),
    own: RecordingParts | None = None,
) -> Path:
    """Write `out_dir/report.html` with its PNGs.

    `calibration` (a `CalibrationResult`) and `base_poses` (from
    `robtraj.estimate._base_frame.base_frame_poses`) when the recording could be put into
    the robot base frame; without them the tool poses are fitted in the camera frame (when
    the recording has a tool) and the calibration section is left out. `deviation` (a
    `DeviationResult`) with `reference` (its `ReferencePath`) and `iso` (an
    `Iso9283Result`) when they could be computed; `notes` (why something was left out)
    go to the summary's warnings. `own`: the sections of the recording and its poses
    alone, from `recording_parts` (of the same `rec` and `base_poses`), when the caller
    computed them already.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    own = recording_parts(out, rec, base_poses) if own is None else own
    poses = own.poses
    parts = [
        _recording_part(rec, name, poses),
        calibration_part(calibration),
        static_pose_part(out, rec, calibration, base_poses),
        iso_part(iso),
        compensation_part(out, rec, calibration, iso),
        deviation_part(out, deviation, reference, poses.position),
        own.speed,
        own.visibility,
        own.noise,
        own.pose_quality,
    ]
    facts = [f for p in parts for f in p.facts]
    warnings = [*notes, *(w for p in parts for w in p.warnings)]
    return write_report(
        out,
        [*(p.section for p in parts if p.section is not None), *extra_sections],
        name=name,
        date=str(rec.attrs.get("created", ""))[:10] or None,
        summary=Summary(facts, warnings),
        title="Robot performance test report (ISO 9283)",
    )


class RecordingParts(NamedTuple):
    """The report's sections that depend on the recording and its tool poses alone: the
    tool poses shown (`ToolPoses`), the TCP speed, the LEDs' visibility and
    moving-window variance, the noise model and the pose fit's quality."""

    poses: ToolPoses
    speed: ReportPart
    visibility: ReportPart
    noise: ReportPart
    pose_quality: ReportPart


def recording_parts(out_dir: str | os.PathLike, rec, base_poses=None) -> RecordingParts:
    """The `RecordingParts` of `rec` (figures into `out_dir`; `base_poses` as in
    `recording_report`). They pass over the LED positions chunk by chunk and over the
    per-frame poses, holding per-frame arrays while they do: a command that also holds
    per-frame results of its own (path deviation, ISO 9283) computes these first, so the
    two are never in memory together."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    poses = tool_poses(rec, base_poses)
    return RecordingParts(
        poses,
        speed_part(out, poses),
        led_part(out, rec, poses),
        noise_part(out, rec),
        pose_quality_part(out, poses),
    )


def _recording_part(rec, name: str, poses: ToolPoses) -> ReportPart:
    """The summary's first lines: the recording, robot log, tool, the frame of the poses
    and the quality of their fit; with the warnings of `poses`."""
    duration = float(rec.time[-1] - rec.time[0]) if rec.n_frames > 1 else 0.0
    robot = rec.robot
    facts = [
        (
            "recording",
            f"{name}: {rec.n_frames} frames over {duration:.1f} s, {rec.n_leds} LEDs"
            + (f", source {rec.attrs['source']}" if rec.attrs.get("source") else ""),
        ),
        (
            "robot",
            "no robot log"
            if robot is None
            else f"{robot.model or 'DH table'}, {np.shape(robot.joints)[1]} joints, "
            f"{np.shape(robot.joints)[0]} log samples",
        ),
        (
            "tool",
            "no tool constellation"
            if rec.tool is None
            else f"{len(rec.tool.led_ids)} LEDs"
            + (
                ", nominal TCP flange←tool at "
                + ", ".join(
                    f"{x:.2f}" for x in np.asarray(rec.tool.flange_from_tool.position) * 1e3
                )
                + " mm"
                if rec.tool.flange_from_tool is not None
                else ", no nominal TCP"
            ),
        ),
        ("poses", poses.frame),
    ]
    est = poses.estimate
    if est is not None:
        facts.append(
            (
                "pose fit",
                f"{est.valid.mean() * 100:.1f} % of frames, median fit RMS "
                f"{np.nanmedian(est.rms) * 1e6:.1f} µm ({est.weighting} weighting)",
            )
        )
    return ReportPart(facts=tuple(facts), warnings=poses.warnings)
