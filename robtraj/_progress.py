"""Progress on stderr for long work (rich): frames done, rate and time left while a
command passes over a recording; silent when stderr is not a terminal or after
`set_quiet` (every command's ``--quiet``)."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text

_quiet = False


def set_quiet(quiet: bool) -> None:
    """Silence (or allow again) every progress display of this process."""
    global _quiet
    _quiet = bool(quiet)


def _enabled(enabled: bool | None) -> bool:
    if _quiet:
        return False
    return sys.stderr.isatty() if enabled is None else enabled


class _Rate(ProgressColumn):
    """Items per second over the last seconds (rich's own estimate)."""

    def __init__(self, unit: str) -> None:
        super().__init__()
        self.unit = unit

    def render(self, task) -> Text:
        speed = task.finished_speed or task.speed
        return Text("" if speed is None else f"{speed:,.0f} {self.unit}/s")


@contextlib.contextmanager
def progress_bar(
    description: str, total: int | float, enabled: bool | None = None, unit: str = "frames"
) -> Iterator:
    """Yields ``advance(n=1)``; on stderr when it is a terminal (or `enabled`) and not
    quiet: a bar with the `unit`s done of `total`, their rate, the time left and the time
    spent."""
    if not _enabled(enabled):
        yield lambda n=1: None
        return
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn(unit),
        _Rate(unit),
        TextColumn("left"),
        TimeRemainingColumn(),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        transient=True,
    ) as p:
        task = p.add_task(description, total=total)
        yield lambda n=1: p.advance(task, n)


@contextlib.contextmanager
def progress_status(description: str, enabled: bool | None = None) -> Iterator:
    """Yields ``say(message)`` for work without a known length: a spinner with the latest
    message and the elapsed time on stderr when it is a terminal (or `enabled`) and not
    quiet."""
    if not _enabled(enabled):
        yield lambda message: None
        return
    with Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        transient=True,
    ) as p:
        task = p.add_task(description, total=None)
        yield lambda message: p.update(task, description=f"{description}: {message}")
