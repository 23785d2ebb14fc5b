"""`robtraj simulate`: write a simulated recording of a scenario."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .._errors import UserError
from . import _output
from ._args import seed


def register(sub) -> argparse.ArgumentParser:
    from ..model import EFFECT_NAMES
    from ..sim import DEFAULT_DURATION, SCENARIOS

    p = sub.add_parser(
        "simulate",
        help="simulate a tracker recording with known truth",
        description=(
            "Simulate an LED-tool recording of the ABB IRB2400-16: tracker at RATE Hz, robot "
            "joint log at 250 Hz, the program, the nominal tool and (unless --no-truth) the truth. "
            "Default durations: "
            + ", ".join(f"{k} {v:g} s" for k, v in DEFAULT_DURATION.items())
            + "."
        ),
    )
    p.add_argument("out", metavar="OUT.h5", help="recording to write (must not exist)")
    p.add_argument("--scenario", default="paper", choices=sorted(SCENARIOS))
    p.add_argument("--seed", type=seed, default=0, help="random seed (>= 0)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="[s]")
    p.add_argument("--rate", type=float, default=1000.0, metavar="HZ", help="tracker rate [Hz]")
    p.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="hide a physical effect (SI units; comma-separated per joint): "
        + ", ".join(EFFECT_NAMES)
        + ", or a dictionary term (e.g. joint2_harmonic1=SIN,COS, or joint2_map=V: a "
        "constant V, or 256 values, one per knot)",
    )
    p.add_argument(
        "--commanded",
        metavar="PROG",
        help="send the controller these poses (a program CSV/JSON, e.g. from `robtraj "
        "compensate`) in place of the scenario's targets, which /program keeps",
    )
    p.add_argument(
        "--ideal-controller",
        action="store_true",
        help="the controller attains what it is sent exactly: no approach, drift or settling "
        "error (the ISO 9283 truths iso_cube injects)",
    )
    p.add_argument("--no-truth", action="store_true", help="leave /truth out of the file")
    p.add_argument("--force", action="store_true", help="overwrite OUT.h5 if it exists")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..model import parse_effect
    from ..sim import simulate_to

    out = Path(args.out)
    _output.check([out], force=args.force)
    if args.duration is not None and not args.duration > 0:
        raise UserError(f"--duration must be > 0 s, got {args.duration}")
    if not args.rate > 0:
        raise UserError(f"--rate must be > 0 Hz, got {args.rate}")
    effects = dict(parse_effect(s) for s in args.effect)
    commanded = None
    if args.commanded is not None:
        from ..importers import read_program

        commanded = read_program(args.commanded)[0].targets
    with _output.new_file(out) as tmp:
        done = simulate_to(
            tmp,
            args.scenario,
            seed=args.seed,
            duration=args.duration,
            rate=args.rate,
            effects=effects,
            truth=not args.no_truth,
            commanded=commanded,
            controller_errors=not args.ideal_controller,
        )
    print(
        f"wrote {out}: {args.scenario}, {done.n_frames} frames at {args.rate:g} Hz "
        f"({done.time_span:.1f} s), {done.n_leds} LEDs, "
        f"{done.seen_mean:.1f} seen per frame on average (min {done.seen_min}), "
        f"effects: {', '.join(_effect_text(k, v) for k, v in effects.items()) or 'none'}"
    )
    return 0


def _effect_text(name: str, value) -> str:
    v = np.asarray(value)
    if v.size > 12:  # a joint angle error map: its range, not its knots
        return f"{name}=[{v.size} values in {v.min():.3g}…{v.max():.3g}]"
    return f"{name}={np.round(v, 9).tolist()}"
