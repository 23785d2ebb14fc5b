"""``robtraj emulate REC.h5 --port URL``: replay a recording as the tracker would stream it."""

from __future__ import annotations

import argparse
import signal
import sys
from typing import Any

from .._errors import UserError
from ..recording import read_recording
from . import _output
from ._args import seed


def register(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "emulate",
        help="replay a recording as the tracker device would stream it (with faults)",
        description=(
            "Serve a recording in the robtraj stream protocol (acquisition/PROTOCOL.md) the "
            "way the device would: frames at the recording's rate, status messages with the "
            "camera temperature, end of stream at the end. socket://HOST:PORT listens on "
            "that port (0: any free port); 'pty' creates a pseudo-terminal and prints its "
            "device path, 'pty:LINK' also keeps a symlink LINK to it (needed to reconnect "
            "after a disconnect fault)."
        ),
        epilog=(
            "faults: comma-separated NAME=VALUE, probabilities per message: corrupt (flip 1-3 "
            "bits), truncate (send a prefix), drop, burst (8-64 bytes of noise over the "
            "stream), noise (8-64 garbage bytes between messages); disconnect=S drops the "
            "connection every S seconds of recording time. Example: "
            "--faults corrupt=0.01,truncate=0.005,drop=0.01,disconnect=1.5"
        ),
    )
    p.add_argument("recording", metavar="REC.h5", help="recording to replay")
    p.add_argument(
        "--port", required=True, metavar="URL", help="socket://HOST:PORT, pty or pty:LINK"
    )
    p.add_argument(
        "--rate", type=float, metavar="HZ", help="frame rate (default: the recording's; 0: unpaced)"
    )
    p.add_argument("--faults", metavar="SPEC", help="faults to inject (see below)")
    p.add_argument("--seed", type=seed, default=0, help="random seed of the faults (default 0)")
    p.add_argument("--ledger", metavar="PATH", help="write the fate of every message (JSON)")
    p.add_argument(
        "--port-file", metavar="PATH", help="write the URL a recorder should open once serving"
    )
    p.add_argument(
        "--client-timeout",
        type=float,
        default=60.0,
        metavar="S",
        help="give up when no recorder connects within S seconds (default 60)",
    )
    p.add_argument("--force", action="store_true", help="overwrite an existing ledger")
    p.set_defaults(func=run)
    return p


def _stop(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    from acquisition.emulator import Emulator, open_transport, parse_faults, write_ledger

    _output.check([args.ledger], force=args.force)
    _output.check([args.port_file], force=True)  # a rendezvous file, rewritten each run
    faults = parse_faults(args.faults)
    if args.rate is not None and not args.rate >= 0:
        raise UserError(f"--rate must be >= 0, got {args.rate}")
    rec = read_recording(args.recording)
    transport = open_transport(args.port)
    emulator = None
    try:
        emulator = Emulator(
            rec,
            transport,
            faults=faults,
            seed=args.seed,
            rate=args.rate,
            client_timeout=args.client_timeout,
        )
        print(
            f"emulating {args.recording} ({rec.n_frames} frames, {rec.n_leds} LEDs, "
            f"{emulator.rate:g} Hz) on {transport.url}",
            file=sys.stderr,
            flush=True,
        )
        if args.port_file:
            _output.write_text(args.port_file, transport.url + "\n")
        signal.signal(signal.SIGTERM, _stop)
        try:
            result = emulator.run()
        except KeyboardInterrupt:
            result = emulator.result()
            print("emulate: stopped", file=sys.stderr)
    finally:
        transport.close()
    if args.ledger:
        write_ledger(result, args.ledger)
    fates = result["messages"]["fate"]
    counts = {f: fates.count(f) for f in sorted(set(fates))}
    print(
        "sent " + ", ".join(f"{n} {f}" for f, n in counts.items()) + " messages",
        file=sys.stderr,
    )
    return 0
