"""`robtraj attach TRACKER.h5 -o RUN.h5`: join a measurement campaign's parts into one recording."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .._errors import UserError
from . import _output


def register(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "attach",
        help="join a campaign: tracker stream + joint log + robot model + tool + program",
        description=(
            "Add what a measurement campaign has beside the tracker stream (from `robtraj "
            "record`): the controller's joint log on its own clock, the robot's model, the "
            "LED tool and the program, each optional, into a new complete recording. The "
            "robot clock's offset is found from the data (the tool's angular and linear "
            "speed seen by the tracker against the joint log's, over every lag) and stored "
            "with its standard error; `calibrate` refines it. Formats: docs/campaign.md."
        ),
    )
    p.add_argument("recording", metavar="TRACKER.h5", help="recording with the tracker stream")
    p.add_argument("-o", "--out", required=True, metavar="RUN.h5", help="new recording to write")
    p.add_argument(
        "--robot-log",
        metavar="LOG",
        help="joint log: UR RTDE CSV, a CSV with --mapping, a ROS 1 .bag or a ROS 2 bag "
        "(folder, .db3 or .mcap) of sensor_msgs/JointState",
    )
    p.add_argument(
        "--log-format",
        choices=["ur-rtde", "csv", "ros1", "ros2"],
        help="format of --robot-log (default: from the file)",
    )
    p.add_argument("--mapping", metavar="JSON", help="generic CSV log: JSON column mapping")
    p.add_argument(
        "--joint-names", metavar="A,B,...", help="ROS bag: joint names in the model's order"
    )
    p.add_argument("--topic", help="ROS bag: the JointState topic (default: the only one)")
    p.add_argument(
        "--robot",
        metavar="MODEL",
        help="robot model: a built-in name (abb_irb2400_16, ur10), a DH JSON or a URDF",
    )
    p.add_argument("--flange-link", metavar="LINK", help="URDF: the flange link (default tool0)")
    p.add_argument(
        "--base-link",
        metavar="LINK",
        help="URDF: the base frame of the program's targets (default the root link; "
        "ur_description: base)",
    )
    p.add_argument("--tool", metavar="TOOL", help="LED tool: JSON or CSV (docs/campaign.md)")
    p.add_argument("--program", metavar="PROG", help="program targets: CSV or JSON")
    p.add_argument(
        "--clock-offset",
        type=float,
        metavar="S",
        help="robot clock minus tracker clock [s], when known (skips the search)",
    )
    p.add_argument("--json", metavar="PATH", help="also write what was attached as JSON")
    p.add_argument("--force", action="store_true", help="overwrite RUN.h5 if it exists")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    if Path(args.out).resolve() == Path(args.recording).resolve():
        raise UserError("-o names the input; attach writes a new recording")
    _output.check([args.out, args.json], force=args.force)
    if not any((args.robot_log, args.robot, args.tool, args.program)):
        raise UserError("nothing to attach: give --robot-log with --robot, --tool or --program")
    names = None if not args.joint_names else [s.strip() for s in args.joint_names.split(",")]
    rec, alignment, parts = attach_files(
        args.recording, robot_log=args.robot_log, log_format=args.log_format,
        mapping=args.mapping, joint_names=names, topic=args.topic, robot=args.robot,
        flange_link=args.flange_link, base_link=args.base_link, tool=args.tool,
        program=args.program,
        clock_offset=args.clock_offset,
    )  # fmt: skip
    from ..recording import write_recording

    write_recording(rec, args.out, overwrite=args.force)
    summary = _summary(rec, alignment, parts)
    print("\n".join(_lines(args.out, summary)))
    if args.json:
        _output.write_text(args.json, json.dumps(summary, indent=1))
    return 0


def attach_files(tracker: str | Path, **files):
    """The recording `robtraj attach` makes of the stream in `tracker` and the campaign's
    `files` (`robtraj.importers.read_parts`), its clock alignment and the parts."""
    from ..importers import attach, read_parts
    from ..recording import read_recording

    rec = read_recording(tracker)
    parts = read_parts(**files)
    return (*attach(rec, parts), parts)


def _summary(rec, alignment, parts) -> dict:
    doc: dict = {"frames": rec.n_frames, "leds": rec.n_leds, "attached": parts.sources}
    if alignment is not None:
        doc["clock"] = {
            "offset_s": alignment.offset,
            "sigma_s": alignment.sigma,
            "correlation": alignment.correlation,
            "channels": list(alignment.channels),
            "from_data": parts.clock_offset is None,
        }
        t = rec.robot.time
        inside = (rec.time >= t[0]) & (rec.time <= t[-1])
        doc["robot"] = {"samples": int(t.size), "joints": int(rec.robot.joints.shape[1]),
                        "covers": float(inside.mean())}  # fmt: skip
    if rec.program is not None:
        doc["program"] = {"targets": int(rec.program.motion.size)}
    return doc


def _lines(out: str, doc: dict) -> list[str]:
    lines = [f"wrote {out}: {doc['frames']} frames, {doc['leds']} LEDs; attached " + ", ".join(
        f"{k.replace('_', ' ')} {v}" for k, v in doc["attached"].items())]  # fmt: skip
    clock = doc.get("clock")
    if clock is not None:
        if clock["from_data"]:
            lines.append(
                f"robot clock = tracker clock + {clock['offset_s']:.4f} s "
                f"(σ {clock['sigma_s'] * 1e3:.2f} ms; the tool's {' and '.join(clock['channels'])} "
                f"speed correlate at {clock['correlation']:.3f}); calibrate refines it as τ"
            )
        else:
            lines.append(f"robot clock = tracker clock + {clock['offset_s']:.4f} s (given)")
        r = doc["robot"]
        lines.append(
            f"joint log: {r['samples']} samples of {r['joints']} joints, covering "
            f"{r['covers']:.1%} of the tracker frames"
        )
    return lines
