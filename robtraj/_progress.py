"""A progress bar for long work (rich), silent when output is not a terminal."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator

from rich.console import Console
from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn


@contextlib.contextmanager
def progress_bar(description: str, total: int | float, enabled: bool | None = None) -> Iterator:
    """Yields ``advance(n=1)``; draws on stderr when it is a terminal (or `enabled`)."""
    console = Console(stderr=True)
    if enabled is None:
        enabled = sys.stderr.isatty()
    if not enabled:
        yield lambda n=1: None
        return
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as p:
        task = p.add_task(description, total=total)
        yield lambda n=1: p.advance(task, n)


@contextlib.contextmanager
def progress_status(description: str, enabled: bool | None = None) -> Iterator:
    """Yields ``say(message)`` for work without a known length: a spinner with the latest
    message and the elapsed time on stderr when it is a terminal (or `enabled`)."""
    console = Console(stderr=True)
    if enabled is None:
        enabled = sys.stderr.isatty()
    if not enabled:
        yield lambda message: None
        return
    with Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as p:
        task = p.add_task(description, total=None)
        yield lambda message: p.update(task, description=f"{description}: {message}")
