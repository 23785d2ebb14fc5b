"""ISO 9283 characteristics in a recording's report: their tables, the worst value of
each key characteristic in the summary, and warnings for what the test lacks."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ._html import Section, Value, interval_of, iso_tables
from ._report_part import ReportPart, left_out
from ._words import column_label

ISO_CYCLES = 30  # cycles ISO 9283 §6.6 asks for per test
# key characteristics in the summary: (block, key), the worst entry of the block
_KEY_CHARACTERISTICS = [
    ("poses", "AP_mm"),
    ("poses", "RP_mm"),
    ("poses", "AP_angle_deg"),
    ("poses", "RP_angle_deg"),
    ("distances", "AD_mm"),
    ("distances", "RD_mm"),
    ("paths", "AT_mm"),
    ("paths", "RT_mm"),
    ("corners", "CR_max_mm"),
]


_WHY = {
    "vAP": "vAP needs approaches from several directions",
    "dAP": "drift needs at least 4 cycles",
    "dRP": "drift needs at least 4 cycles",
}


def _symbol(key: str) -> str:
    """The characteristic's symbol of a JSON key: ``"t_stab_mean_s"`` → ``"t_stab_mean"``."""
    for suffix in ("_mm_per_s", "_percent", "_deg", "_mm", "_s"):
        if key.endswith(suffix):
            return key[: -len(suffix)]
    return key


def _key_facts(iso_json: Mapping[str, Any]) -> tuple[list[tuple[str, Any]], list[str]]:
    """Summary rows (worst pose/path per characteristic, with its interval) and warnings
    (too few cycles, characteristics without a value)."""
    facts, warnings = [], []
    for block, key in _KEY_CHARACTERISTICS:
        entries = {n: v for n, v in iso_json.get(block, {}).items() if v.get(key) is not None}
        if not entries:
            continue
        name = max(entries, key=lambda n: abs(entries[n][key]))
        facts.append(
            (
                f"{column_label(key)}, worst ({name})",
                Value(entries[name][key], interval_of(entries[name], key)),
            )
        )
    for block in ("poses", "paths"):
        cycles = {n: v.get("n_cycles") for n, v in iso_json.get(block, {}).items()}
        cycles = {n: c for n, c in cycles.items() if c}
        if cycles and min(cycles.values()) < ISO_CYCLES:
            lo, hi = min(cycles.values()), max(cycles.values())
            span = f"{lo}" if lo == hi else f"{lo}–{hi}"
            warnings.append(
                f"ISO 9283 {block}: {span} cycles per {block[:-1]}, the standard asks for "
                f"{ISO_CYCLES}; the characteristics scatter more than in a full test."
            )
        entries = iso_json.get(block, {})
        empty = [n for n, v in entries.items() if v.get("n_cycles") == 0]
        if empty:
            warnings.append(
                f"ISO 9283 {block} {', '.join(empty)}: no complete cycle measured, so no "
                "characteristics."
            )
        missing: dict[tuple[str, ...], list[str]] = {}
        for k in {k for n, v in entries.items() if n not in empty for k in v}:
            names = tuple(n for n, v in entries.items() if n not in empty and v.get(k, 0) is None)
            if names:
                missing.setdefault(names, []).append(_symbol(k))
        for names, keys in missing.items():
            warnings.append(
                f"ISO 9283 {block} {', '.join(names)}: no value (NaN) for "
                f"{', '.join(sorted(keys))}"
                + "".join(
                    f" ({w})" for w in dict.fromkeys(_WHY[k] for k in sorted(keys) if k in _WHY)
                )
                + "."
            )
    return facts, warnings


def iso_part(iso) -> ReportPart:
    """The section of an `Iso9283Result` with its key facts and warnings; left out
    without one."""
    if iso is None:
        return left_out(
            "ISO 9283 characteristics",
            "needs a program (/program) with repeated poses or moves and base-frame "
            "poses; see the notes in the summary.",
        )
    iso_json = iso.to_json()
    facts, warnings = _key_facts(iso_json)
    section = Section(
        "ISO 9283 characteristics",
        "Measured TCP (the controller's TCP carried by the measured flange) against "
        "the program, per test pose and repeated path; value [lo, hi] where a 95 % "
        "confidence interval from the cycles is available.",
        tables=iso_tables(iso_json),
    )
    return ReportPart(section, tuple(facts), tuple(warnings))
