"""One part of a recording's report: its section and what it adds to the summary."""

from __future__ import annotations

import dataclasses
from typing import Any

from ._html import Section


@dataclasses.dataclass(frozen=True)
class ReportPart:
    """What one step of `recording_report` contributes: a `section` (None for none), the
    summary's `facts` (label, value) and its `warnings` (sentences)."""

    section: Section | None = None
    facts: tuple[tuple[str, Any], ...] = ()
    warnings: tuple[str, ...] = ()


def left_out(title: str, reason: str) -> ReportPart:
    """A section that only says why it is left out."""
    return ReportPart(Section(title, f"Left out: {reason}"))
