"""``robtraj record --port URL -o REC.h5``: record the tracker stream to a schema-1 file."""

from __future__ import annotations

import argparse
import os
import signal
import sys
from typing import Any

from .._errors import UserError
from . import _output


def register(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "record",
        help="record the tracker's stream into a schema-1 recording",
        description=(
            "Read the device stream from any pyserial URL (/dev/ttyUSB0, socket://HOST:PORT, "
            "a pty, loop://) and write a schema-1 HDF5 recording while recording, flushed "
            "every 0.5 s: a crash loses at most the last second. Corrupted bytes, truncated "
            "messages, lost frames and disconnects (reconnect with back-off) are counted and "
            "the recording goes on. SIGINT/SIGTERM stop it cleanly. The LED set is fixed "
            "from the first 0.5 s of the stream."
        ),
    )
    p.add_argument("--port", required=True, metavar="URL", help="pyserial URL of the device")
    p.add_argument("-o", "--out", required=True, metavar="REC.h5", help="recording to write")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    p.add_argument(
        "--protocol", default="robtraj", help="stream protocol: robtraj (default) or natnet"
    )
    p.add_argument("--force", action="store_true", help="overwrite an existing output")
    p.add_argument(
        "--reconnect-timeout",
        type=float,
        default=30.0,
        metavar="S",
        help="give up after S seconds without a connection (default 30)",
    )
    p.add_argument(
        "--compression",
        choices=["gzip", "lzf", "none"],
        default="gzip",
        help="compression of positions and status (default gzip; none needs least CPU)",
    )
    p.add_argument("--quiet", action="store_true", help="no live progress line")
    p.add_argument("--json", metavar="PATH", help="write the summary and error counts (JSON)")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from acquisition.recorder import Recorder, format_summary

    if args.duration is not None and not args.duration > 0:
        raise UserError(f"--duration must be > 0 s, got {args.duration}")
    if not args.reconnect_timeout >= 0:
        raise UserError(f"--reconnect-timeout must be >= 0 s, got {args.reconnect_timeout}")
    # the recording itself is written in place while recording (a crash keeps what was
    # flushed), so only the checks of the output rule apply to it
    _output.check([args.out, args.json], force=args.force)
    recorder = Recorder(
        args.port,
        args.out,
        protocol=args.protocol,
        duration=args.duration,
        force=args.force,
        reconnect_timeout=args.reconnect_timeout,
        progress=None if args.quiet else sys.stderr,
        compression=None if args.compression == "none" else args.compression,
    )

    def stop(signum: int, frame: Any) -> None:
        recorder.request_stop()

    old = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        summary = recorder.run()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    _output.write_json(args.json, summary, indent=1)
    print(format_summary(summary), file=sys.stderr)
    reason = summary["stop_reason"]
    if reason == "disk_full":
        print(
            f"robtraj: error: disk full while writing {args.out} ({summary['message']}); "
            f"stopped, the file keeps the {summary['written']} frames flushed before",
            file=sys.stderr,
            flush=True,
        )
        sys.stdout.flush()
        os._exit(1)  # the HDF5 library is in an error state: leave without tearing it down
    if reason == "connection_lost":
        print(
            f"robtraj: error: lost the connection to {args.port} for "
            f"{args.reconnect_timeout:g} s ({summary['message']}); kept "
            f"{summary['written']} frames",
            file=sys.stderr,
        )
        return 1
    return 0
