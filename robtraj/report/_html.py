"""A one-page HTML report: header, sections of text, figures (linked PNGs) and tables."""

from __future__ import annotations

import dataclasses
import datetime
import html
import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any


@dataclasses.dataclass(frozen=True)
class Table:
    """A titled table: `columns` (header strings) and `rows` (one sequence per row)."""

    title: str
    columns: Sequence[str]
    rows: Sequence[Sequence[Any]]

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
    """One report section: a heading, a short text, figure files and tables."""

    title: str
    text: str = ""
    figures: Sequence[str | os.PathLike] = ()
    tables: Sequence[Table] = ()


def iso_tables(iso_json: Mapping[str, Mapping[str, Any]]) -> list[Table]:
    """Tables from `Iso9283Result.to_json()`: poses, distances, paths, corners (non-empty ones)."""
    titles = {
        "poses": "Pose characteristics (ISO 9283 §7)",
        "distances": "Distance accuracy and repeatability (ISO 9283 §7.4)",
        "paths": "Path characteristics (ISO 9283 §8)",
        "corners": "Corner deviations (ISO 9283 §8.5)",
    }
    out = []
    for key, title in titles.items():
        block = {
            name: {k: v for k, v in values.items() if not isinstance(v, list)}
            for name, values in iso_json.get(key, {}).items()
        }
        if block:
            out.append(Table.from_mapping(title, block, first=key[:-1]))
    return out


def _cell(v: Any) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { margin-bottom: 0.1em; } .meta { color: #666; margin-top: 0; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.85em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.5em; text-align: right; }
th { background: #f0f0f0; } td:first-child, th:first-child { text-align: left; }
figure { margin: 1em 0; } img { max-width: 100%; border: 1px solid #ddd; }
figcaption { color: #555; font-size: 0.9em; }
"""


def write_report(
    out_dir: str | os.PathLike,
    sections: Sequence[Section],
    *,
    name: str = "recording",
    date: str | None = None,
    filename: str = "report.html",
) -> Path:
    """Write `out_dir/filename`, an HTML page with one part per `Section`.

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
        f"<title>robtraj report: {html.escape(name)}</title><style>{_CSS}</style></head><body>",
        f"<h1>robtraj report: {html.escape(name)}</h1>",
        f'<p class="meta">recording date {html.escape(str(date))}; units: mm, µm, degrees, '
        "seconds as labelled</p>",
    ]
    for sec in sections:
        parts.append(f"<h2>{html.escape(sec.title)}</h2>")
        if sec.text:
            parts.append(f"<p>{html.escape(sec.text)}</p>")
        for fig in sec.figures:
            fig = Path(fig)
            try:
                rel = fig.resolve().relative_to(out.resolve())
            except ValueError:
                shutil.copy2(fig, out / fig.name)
                rel = Path(fig.name)
            src = html.escape(rel.as_posix())
            parts.append(
                f'<figure><a href="{src}"><img src="{src}" alt="{html.escape(fig.stem)}"></a>'
                f"<figcaption>{html.escape(fig.stem.replace('_', ' '))}</figcaption></figure>"
            )
        for table in sec.tables:
            parts.append(f"<h3>{html.escape(table.title)}</h3><table><thead><tr>")
            parts += [f"<th>{html.escape(str(c))}</th>" for c in table.columns]
            parts.append("</tr></thead><tbody>")
            for row in table.rows:
                parts.append("<tr>" + "".join(f"<td>{_cell(v)}</td>" for v in row) + "</tr>")
            parts.append("</tbody></table>")
    parts.append("</body></html>")
    path = out / filename
    path.write_text("\n".join(parts), encoding="utf-8")
    return path
