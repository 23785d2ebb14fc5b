"""The `robtraj` command (DESIGN section 8).

Each subcommand lives in its own module ``robtraj/cli/_<name>.py`` exposing
``register(subparsers) -> argparse.ArgumentParser`` whose parser sets
``func=run``; ``run(args) -> int`` is a thin layer: open the input, call one pure
function, write a new file, print. A `UserError` (bad input a user can fix) becomes
one line ``robtraj: error: …`` and exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from .._errors import UserError

# name -> module; a module that is not there yet is skipped (its command is not offered).
_COMMANDS = [
    "demo",
    "simulate",
    "poses",
    "calibrate",
    "iso9283",
    "deviation",
    "discrepancy",
    "evaluate",
    "report",
    "import",
    "attach",
    "export",
    "compensate",
    "emulate",
    "record",
]
#: commands that compile JAX kernels: they use the persistent compilation cache
_COMPILING = {
    "demo", "poses", "calibrate", "iso9283", "deviation", "discrepancy", "evaluate", "report",
    "attach", "compensate",
}  # fmt: skip


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse prints usage too)
        self.exit(2, f"robtraj: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="robtraj",
        description=(
            "Measure what an industrial robot really does: LED-tracker recordings to 6-DOF "
            "tool poses, calibration, ISO 9283 characteristics and discrepancy discovery."
        ),
    )
    from .. import __version__

    parser.add_argument("--version", action="version", version=f"robtraj {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in _COMMANDS:
        try:
            module = importlib.import_module(f"._{name}", __name__)
        except ModuleNotFoundError as e:
            if e.name and e.name.endswith(f"._{name}"):
                continue
            raise
        command = module.register(sub)
        if not any(a.dest == "quiet" for a in command._actions):
            command.add_argument(
                "--quiet", action="store_true", help="no progress display on stderr"
            )
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from .._progress import set_quiet

    set_quiet(args.quiet)
    if args.command in _COMPILING:
        from .._heap import return_freed_memory
        from .._jax_cache import enable_compilation_cache

        enable_compilation_cache()
        return_freed_memory()
    try:
        code = args.func(args)
    except UserError as e:
        print(f"robtraj: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("robtraj: interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
