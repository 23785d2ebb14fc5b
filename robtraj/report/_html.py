"""A one-page HTML report: summary, sections of text, captioned figures, tables, glossary."""

from __future__ import annotations

import dataclasses
import datetime
import html
import math
import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ._words import CAPTIONS, GLOSSARY, column_label


@dataclasses.dataclass(frozen=True)
class Value:
    """A value (a number, or text) with an optional interval `(lo, hi)` (e.g. a 95 %
    confidence interval), rendered as ``value [lo, hi]``; `None` or NaN as "–"."""

    value: Any
    interval: tuple[float, float] | None = None


@dataclasses.dataclass(frozen=True)
class Figure:
    """A PNG file and the caption shown under it."""

    path: str | os.PathLike
    caption: str


@dataclasses.dataclass(frozen=True)
class Table:
    """A titled table: `columns` (header strings) and `rows` (one sequence per row); a
    cell may be a `Value`. `caption` says what the table shows."""

    title: str
    columns: Sequence[str]
    rows: Sequence[Sequence[Any]]
    caption: str = ""

    @classmethod
    def from_mapping(cls, title: str, data: Mapping[str, Mapping[str, Any]], first: str = "name"):
        """Rows from `{row name: {column: value}}` (e.g. one block of `Iso9283Result.to_json()`);
        columns are the union of the inner keys, in first-seen order."""
        cols: list[str] = []
        for inner in data.values():
            cols += [k for k in inner if k not in cols]
        rows = [[name, *(inner.get(c) for c in cols)] for name, inner in data.items()]
        return cls(title, [first, *cols], rows)


@dataclasses.dataclass(frozen=True)
class Section:
    """One report section: a heading, a short text, figures (`Figure` or a path, then
    captioned by its file name) and tables."""

    title: str
    text: str = ""
    figures: Sequence[Figure | str | os.PathLike] = ()
    tables: Sequence[Table] = ()


@dataclasses.dataclass(frozen=True)
class Summary:
    """The box at the top: `facts` (label, value) rows and `warnings` (sentences)."""

    facts: Sequence[tuple[str, Any]]
    warnings: Sequence[str] = ()


def interval_of(block: Mapping[str, Any], key: str) -> tuple[float, float] | None:
    """The interval of `block[key]` when the block carries one: ``block[key + "_ci95"]``
    or ``block["ci95"][key]``, a pair `[lo, hi]`; otherwise None."""
    ci = block.get(f"{key}_ci95")
    if ci is None and isinstance(block.get("ci95"), Mapping):
        ci = block["ci95"].get(key)
    if isinstance(ci, Sequence) and len(ci) == 2 and all(_finite(c) for c in ci):
        return float(ci[0]), float(ci[1])
    return None


def _finite(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


_ISO_BLOCKS = {
    "poses": (
        "Pose characteristics (ISO 9283 §7)",
        "One column per test pose: accuracy and repeatability of position and orientation "
        "over the cycles in which the pose was attained.",
    ),
    "distances": (
        "Distance accuracy and repeatability (ISO 9283 §7.4)",
        "One column per pair of test poses attained one after the other.",
    ),
    "paths": (
        "Path characteristics (ISO 9283 §8)",
        "One column per repeated linear move (start pose → end pose).",
    ),
    "corners": (
        "Corner deviations (ISO 9283 §8.5)",
        "One column per corner between two linear moves.",
    ),
}
_MAX_COLUMNS = 6  # pose columns per transposed table: keeps it within the page


def iso_tables(iso_json: Mapping[str, Mapping[str, Any]]) -> list[Table]:
    """Tables from `Iso9283Result.to_json()` (non-empty blocks), transposed: one row per
    characteristic (header in words with its unit), one column per pose/path, at most six
    per table. A characteristic with an interval (see `interval_of`) shows it."""
    out = []
    for key, (title, caption) in _ISO_BLOCKS.items():
        block = iso_json.get(key, {})
        names = list(block)
        if not names:
            continue
        chars: list[str] = []
        for values in block.values():
            chars += [
                k
                for k, v in values.items()
                if k not in chars
                and k != "ci95"
                and not k.endswith("_ci95")
                and not isinstance(v, list)
            ]
        for i in range(0, len(names), _MAX_COLUMNS):
            part = names[i : i + _MAX_COLUMNS]
            rows = [
                [column_label(c), *(Value(block[n].get(c), interval_of(block[n], c)) for n in part)]
                for c in chars
            ]
            more = (
                f" (columns {i + 1}–{i + len(part)} of {len(names)})"
                if len(names) > _MAX_COLUMNS
                else ""
            )
            out.append(Table(title + more, ["characteristic", *part], rows, caption))
    return out


def _number(v: float) -> str:
    return f"{v:.4g}"


def _cell(v: Any) -> str:
    if isinstance(v, Value):
        if v.value is None or (isinstance(v.value, float) and not math.isfinite(v.value)):
            return "–"
        text = _cell(v.value)
        if v.interval is not None:
            lo, hi = v.interval
            text += f' <span class="ci">[{_number(lo)}, {_number(hi)}]</span>'
        return text
    if v is None:
        return "–"
    if isinstance(v, float):
        return _number(v) if math.isfinite(v) else "–"
    return html.escape(str(v))


_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; padding: 0 1em;
       color: #222; }
h1 { margin-bottom: 0.1em; } .meta { color: #666; margin-top: 0; }
table { border-collapse: collapse; margin: 0.3em 0 0.3em; font-size: 0.85em; max-width: 100%; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.5em; text-align: right;
         overflow-wrap: anywhere; }
th { background: #f0f0f0; } td:first-child, th:first-child { text-align: left; }
.caption, figcaption { color: #555; font-size: 0.9em; margin: 0 0 1.5em; max-width: 60em; }
.ci { color: #666; white-space: nowrap; }
figure { margin: 1em 0; } img { max-width: 100%; border: 1px solid #ddd; }
.summary { border: 2px solid #446; padding: 0.5em 1em; background: #f7f7fb; }
.summary table { font-size: 0.95em; } .summary td { text-align: left; }
.warn { color: #8a3a00; } .warn li { margin: 0.2em 0; }
dl.glossary dt { font-weight: bold; float: left; clear: left; width: 7em; }
dl.glossary dd { margin: 0 0 0.3em 8em; }
"""


def _table_html(table: Table) -> list[str]:
    parts = [f"<h3>{html.escape(table.title)}</h3><table><thead><tr>"]
    parts += [f"<th>{html.escape(str(c))}</th>" for c in table.columns]
    parts.append("</tr></thead><tbody>")
    for row in table.rows:
        parts.append("<tr>" + "".join(f"<td>{_cell(v)}</td>" for v in row) + "</tr>")
    parts.append("</tbody></table>")
    if table.caption:
        parts.append(f'<p class="caption">{html.escape(table.caption)}</p>')
    return parts


def _figure_html(fig: Figure | str | os.PathLike, out: Path) -> str:
    caption = fig.caption if isinstance(fig, Figure) else None
    path = Path(fig.path if isinstance(fig, Figure) else fig)
    try:
        rel = path.resolve().relative_to(out.resolve())
    except ValueError:
        shutil.copy2(path, out / path.name)
        rel = Path(path.name)
    src = html.escape(rel.as_posix())
    caption = caption or CAPTIONS.get(path.stem) or path.stem.replace("_", " ")
    return (
        f'<figure><a href="{src}"><img src="{src}" alt="{html.escape(caption)}"></a>'
        f"<figcaption>{html.escape(caption)}</figcaption></figure>"
    )


def _used_symbols(sections: Sequence[Section], summary: Summary | None) -> list[str]:
    text = " ".join(
        " ".join(str(c) for t in s.tables for c in [*t.columns, *(r[0] for r in t.rows)])
        for s in sections
    )
    if summary is not None:
        text += " " + " ".join(str(label) for label, _ in summary.facts)
    words = set(text.replace(",", " ").replace("(", " ").replace(")", " ").split())
    cells = [v for s in sections for t in s.tables for r in t.rows for v in r]
    if summary is not None:
        cells += [v for _, v in summary.facts]
    if any(isinstance(v, Value) and v.interval is not None for v in cells):
        words.add("[lo, hi]")
    return [sym for sym in GLOSSARY if sym in words]


def write_report(
    out_dir: str | os.PathLike,
    sections: Sequence[Section],
    *,
    name: str = "recording",
    date: str | None = None,
    filename: str = "report.html",
    summary: Summary | None = None,
    title: str = "robtraj report",
) -> Path:
    """Write `out_dir/filename`, an HTML page: `summary` at the top, one part per
    `Section`, and a glossary of the symbols its tables use.

    Figures are linked by relative path; one that is not inside `out_dir` is copied
    there first, so the folder is self-contained (move or zip it as a whole). The header
    names the recording (`name`) and its `date` (default: today, ISO 8601).

    **Returns:** the path of the HTML file.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    date = date or datetime.date.today().isoformat()
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}: {html.escape(name)}</title><style>{_CSS}</style></head>"
        "<body>",
        f"<h1>{html.escape(title)}: {html.escape(name)}</h1>",
        f'<p class="meta">recording date {html.escape(str(date))}; report written '
        f"{datetime.date.today().isoformat()} by robtraj; units as labelled (mm, µm, degrees, "
        "seconds)</p>",
    ]
    if summary is not None:
        parts.append('<div class="summary"><h2>Summary</h2><table><tbody>')
        for label, value in summary.facts:
            parts.append(f"<tr><th>{html.escape(str(label))}</th><td>{_cell(value)}</td></tr>")
        parts.append("</tbody></table>")
        if summary.warnings:
            parts.append('<h3 class="warn">Warnings and notes</h3><ul class="warn">')
            parts += [f"<li>{html.escape(w)}</li>" for w in summary.warnings]
            parts.append("</ul>")
        parts.append("</div>")
    for sec in sections:
        parts.append(f"<h2>{html.escape(sec.title)}</h2>")
        if sec.text:
            parts.append(f"<p>{html.escape(sec.text)}</p>")
        parts += [_figure_html(fig, out) for fig in sec.figures]
        for table in sec.tables:
            parts += _table_html(table)
    symbols = _used_symbols(sections, summary)
    if symbols:
        parts.append('<h2>Glossary</h2><dl class="glossary">')
        parts += [f"<dt>{html.escape(s)}</dt><dd>{html.escape(GLOSSARY[s])}</dd>" for s in symbols]
        parts.append("</dl>")
    parts.append("</body></html>")
    path = out / filename
    path.write_text("\n".join(parts), encoding="utf-8")
    return path
