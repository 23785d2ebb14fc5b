"""Join a measurement campaign's parts into one schema-1 recording (`robtraj attach`).

A lab has the tracker stream (`robtraj record`), the controller's joint log on its own
clock, the robot's model, the LED tool and the program, each in a file of its own.
`attach` puts them beside the stream: the joint log moved onto the tracker clock by the
offset found from the data (`robtraj.estimate.align_clocks`), which is stored with its
standard error so that `calibrate` refines τ from there.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .._errors import UserError
from ..estimate import (
    ClockAlignment,
    align_clocks,
    robot_speeds,
    stream_speeds,
    tool_poses,
    tracker_speeds,
)
from ..jax_ops import rotation_angle
from ..model import robot_from_log
from ..recording import Pose, Program, Recording, RobotLog, Tool
from ._common import load_constellation
from ._program import read_program
from ._robot_log import JointLog, guess_joint_log_format, read_joint_log
from ._robot_model import RobotDescription, read_robot_model

#: share of the stream the joint log must cover once on the tracker clock
MIN_COVER = 0.5


@dataclasses.dataclass(frozen=True)
class Parts:
    """What a campaign brings beside the stream, each optional: `joint_log` (needs
    `robot`), `robot`, `tool`, `program` (with its per-target `program_extra` columns),
    `clock_offset` [s] (robot − tracker) when the user knows it, and `sources`: the file
    each part came from (stored with the recording)."""

    joint_log: JointLog | None = None
    robot: RobotDescription | None = None
    tool: Tool | None = None
    program: Program | None = None
    program_extra: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    clock_offset: float | None = None
    sources: dict[str, str] = dataclasses.field(default_factory=dict)


def read_parts(
    *,
    robot_log: str | os.PathLike | None = None,
    log_format: str | None = None,
    mapping: str | os.PathLike | None = None,
    joint_names: Sequence[str] | None = None,
    topic: str | None = None,
    robot: str | os.PathLike | None = None,
    flange_link: str | None = None,
    base_link: str | None = None,
    tool: str | os.PathLike | None = None,
    program: str | os.PathLike | None = None,
    clock_offset: float | None = None,
) -> Parts:
    """Each part of a campaign from its file (`read_joint_log`, `read_robot_model`,
    `load_constellation`, `read_program`); `UserError` (one line) where a file is wrong."""
    parts: dict = {"clock_offset": clock_offset, "sources": {}}
    if robot is not None:
        parts["robot"] = read_robot_model(robot, flange_link=flange_link, base_link=base_link)
        parts["sources"]["robot"] = Path(robot).name
    if robot_log is not None:
        fmt = log_format or guess_joint_log_format(robot_log, mapping)
        if joint_names is None and fmt in ("ros1", "ros2") and robot is not None:
            joint_names = parts["robot"].joint_names or None  # the URDF's chain, in order
        parts["joint_log"] = read_joint_log(
            robot_log, format=fmt, mapping=mapping, joint_names=joint_names, topic=topic
        )
        parts["sources"]["robot_log"] = Path(robot_log).name
    if tool is not None:
        parts["tool"] = load_constellation(tool)
        parts["sources"]["tool"] = Path(tool).name
    if program is not None:
        parts["program"], parts["program_extra"] = read_program(program)
        parts["sources"]["program"] = Path(program).name
    return Parts(**parts)


def attach(tracker: Recording, parts: Parts) -> tuple[Recording, ClockAlignment | None]:
    """`tracker` with the campaign's `parts` added, and the clock alignment (None when
    no joint log was attached). `UserError` (one line) for parts that do not fit."""
    _check_not_there(tracker, parts)
    tool = _checked_tool(tracker, parts.tool)
    robot, alignment = _robot_on_tracker_clock(tracker, parts, tool)
    extras = dict(tracker.extras)
    if parts.joint_log is not None and parts.joint_log.commanded is not None:
        extras["robot/joints_commanded"] = np.asarray(parts.joint_log.commanded, np.float64)
    extras.update({f"program/{k}": v for k, v in parts.program_extra.items()})
    attrs = dict(tracker.attrs)
    if parts.sources:
        attrs["attached"] = ", ".join(f"{k}={v}" for k, v in sorted(parts.sources.items()))
    rec = tracker.replace(
        robot=robot if robot is not None else tracker.robot,
        tool=tool if parts.tool is not None else tracker.tool,
        program=parts.program if parts.program is not None else tracker.program,
        extras=extras,
        attrs=attrs,
    )
    return _with_segments(rec), alignment


def _with_segments(rec: Recording) -> Recording:
    """`rec` with `/program/segment` from its joint log where it has none and the log
    executes the program (`program_segments`)."""
    if rec.program is None or rec.robot is None or rec.program.segment is not None:
        return rec
    robot = robot_from_log(rec.robot)
    tcp = tool_poses(robot, rec.robot.joints, rec.tool.flange_from_tool if rec.tool else None)
    segment, _ = program_segments(rec.time, rec.robot.time, tcp, rec.program.targets)
    if segment is None:
        return rec
    return rec.replace(program=dataclasses.replace(rec.program, segment=segment))


def _check_not_there(tracker: Recording, parts: Parts) -> None:
    for name, given, there in (
        ("a robot log (/robot)", parts.joint_log is not None or parts.robot is not None,
         tracker.robot is not None),
        ("a tool (/tool)", parts.tool is not None, tracker.tool is not None),
        ("a program (/program)", parts.program is not None, tracker.program is not None),
    ):  # fmt: skip
        if given and there:
            raise UserError(
                f"the recording already holds {name}; attach adds parts a recording lacks"
            )
    if parts.joint_log is not None and parts.robot is None:
        raise UserError("--robot-log needs --robot (a built-in name, a DH JSON or a URDF)")
    if parts.robot is not None and parts.joint_log is None:
        raise UserError("--robot needs --robot-log: the joint angles the model turns into poses")


def _checked_tool(tracker: Recording, tool: Tool | None) -> Tool | None:
    """The tool to use for the stream, checked against the stream's LED ids."""
    if tool is None:
        return tracker.tool
    ids = np.asarray(tool.led_ids)
    missing = ids[~np.isin(ids, np.asarray(tracker.led_ids))]
    if missing.size:
        shown = ", ".join(str(int(i)) for i in missing[:8]) + (", …" if missing.size > 8 else "")
        raise UserError(
            f"the tool's LED ids {shown} are not in the stream's /tracker/led_ids "
            f"({', '.join(str(int(i)) for i in np.asarray(tracker.led_ids)[:8])}"
            f"{', …' if tracker.led_ids.size > 8 else ''}): is it the tool of this recording?"
        )
    return tool


def _robot_on_tracker_clock(
    tracker: Recording, parts: Parts, tool: Tool | None
) -> tuple[RobotLog | None, ClockAlignment | None]:
    log, desc = parts.joint_log, parts.robot
    if log is None:
        return None, None
    raw = desc.robot_log(log.time, log.joints)
    robot = robot_from_log(raw)
    if log.joints.shape[1] != robot.n_joints:
        raise UserError(
            f"the joint log has {log.joints.shape[1]} joints, the robot model "
            f"{desc.name} {robot.n_joints}"
        )
    if parts.clock_offset is not None:
        alignment = ClockAlignment(float(parts.clock_offset), 0.0, float("nan"), (), 1.0)
    else:
        alignment = _aligned(tracker, robot, log, tool)
    time = np.asarray(log.time, np.float64) - alignment.offset
    _check_cover(tracker.time, time)
    on_tracker = dataclasses.replace(
        raw,
        time=time,
        clock_offset=alignment.offset,
        clock_offset_sigma=alignment.sigma,
    )
    return on_tracker, alignment


def _aligned(tracker: Recording, robot, log: JointLog, tool: Tool | None) -> ClockAlignment:
    if tool is not None:
        cols = {int(i): k for k, i in enumerate(np.asarray(tracker.led_ids))}
        take = [cols[int(i)] for i in np.asarray(tool.led_ids)]
        trk = tracker_speeds(tracker.time, tracker.positions[:, take], tool.constellation)
    else:
        trk = stream_speeds(tracker.time, tracker.positions)
    rob = robot_speeds(robot, log.time, log.joints, None if tool is None else tool.flange_from_tool)
    return align_clocks(trk, rob)


def _check_cover(tracker_time: np.ndarray, robot_time: np.ndarray) -> None:
    t = np.asarray(tracker_time, np.float64)
    inside = (t >= robot_time[0]) & (t <= robot_time[-1])
    if inside.mean() < MIN_COVER:
        raise UserError(
            f"the joint log covers {inside.mean():.0%} of the tracker stream at the clock "
            f"offset (tracker {t[0]:.3f}–{t[-1]:.3f} s, log {robot_time[0]:.3f}–"
            f"{robot_time[-1]:.3f} s on the tracker clock); does the log overlap the stream?"
        )


#: [m] how near the TCP (nominal kinematics of the logged joints) comes to a target it reaches
REACH = 5e-3
#: [rad] likewise for its orientation
REACH_ANGLE = 0.01
#: [m/s] TCP speed below which the robot counts as at rest (above encoder noise)
AT_REST = 2e-3
#: [rad/s] likewise for its rate of turn
AT_REST_ANGULAR = 2e-3


def program_segments(
    tracker_time: np.ndarray, robot_time: np.ndarray, tcp: Pose, targets: Pose
) -> tuple[np.ndarray | None, int]:
    """`(N,)` index of the program target each tracker frame moves to or dwells at (the
    last target whose move has started, as `/program/segment`), from the joint log:
    `tcp` `(K, ·)` (base frame) at `robot_time` (tracker clock) against the program's
    `targets` `(P, ·)`; and the number of targets reached. Targets are reached in the
    program's order (within `REACH` and `REACH_ANGLE`); the move to target j starts when the TCP last rests before
    reaching it. A log that ends early leaves the rest of the program unstarted; one
    reaching fewer than two targets in order (a fly-by program, another program) gives
    None."""
    p, q = tcp.position, tcp.quaternion_wxyz
    speed = np.linalg.norm(np.gradient(p, robot_time, axis=0), axis=1)
    turn = np.asarray(rotation_angle(jnp.asarray(q[:-1]), jnp.asarray(q[1:])))
    rate = turn / np.diff(robot_time)
    turning = np.concatenate([rate[:1], np.maximum(rate[1:], rate[:-1]), rate[-1:]])
    rest = (speed < AT_REST) & (turning < AT_REST_ANGULAR)

    def reached(j: int, k: int) -> int | None:
        """The first sample from `k` on at target j, None if there is none."""
        near = np.linalg.norm(p[k:] - targets.position[j], axis=1) < REACH
        near &= np.abs(q[k:] @ targets.quaternion_wxyz[j]) > np.cos(REACH_ANGLE / 2)
        hits = np.flatnonzero(near)
        return k + int(hits[0]) if hits.size else None

    k, starts = reached(0, 0), [-np.inf]
    if k is None:
        return None, 0
    for j in range(1, targets.position.shape[0]):
        arrive = reached(j, k)
        if arrive is None:
            break
        resting = np.flatnonzero(rest[k:arrive])
        starts.append(robot_time[k + int(resting[-1]) if resting.size else k])
        k = arrive
    if len(starts) < 2:
        return None, len(starts)
    segment = np.searchsorted(np.asarray(starts), tracker_time, side="left") - 1
    return segment.astype(np.int32), len(starts)
