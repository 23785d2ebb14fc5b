"""The one rule for everything a command writes (files and folders).

Checked before any computation (`check`): the folder an output goes into exists, and an
output that is already there is refused unless ``--force`` (a folder counts as there
when it holds anything). Written through a temporary name in the same folder and renamed
into place only when complete (`new_file`, `new_folder`), so a failure or an interrupt
leaves nothing partial behind and never touches what was there before.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from .._errors import UserError


def _target(path: str | os.PathLike | None) -> Path | None:
    return None if path is None or str(path) == "-" else Path(path)


def check(
    files: Iterable[str | os.PathLike | None] = (),
    folders: Iterable[str | os.PathLike | None] = (),
    *,
    force: bool = False,
) -> None:
    """Refuse (`UserError`) outputs that cannot be written or would overwrite without
    `force`: `files` are file paths (None or ``-`` for stdout are skipped), `folders`
    output folders."""
    for f in map(_target, files):
        if f is None:
            continue
        parent = f.parent
        if not parent.is_dir():
            raise UserError(f"{f}: the folder {parent} does not exist")
        if f.is_dir():
            raise UserError(f"{f} is a folder; name a file")
        if f.exists() and not force:
            raise UserError(f"{f} exists; choose another name or pass --force")
    for d in map(_target, folders):
        if d is None:
            continue
        if not d.parent.is_dir():
            raise UserError(f"{d}: the folder {d.parent} does not exist")
        if d.exists() and not d.is_dir():
            raise UserError(f"{d} exists and is not a folder")
        if d.is_dir() and any(d.iterdir()) and not force:
            raise UserError(f"{d} holds earlier results; choose another folder or pass --force")


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


@contextlib.contextmanager
def new_file(path: str | os.PathLike) -> Iterator[Path]:
    """Yields a temporary path beside `path` to write; renamed to `path` on success,
    removed on failure."""
    path = Path(path)
    tmp = _tmp_name(path)
    _remove(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        _remove(tmp)


def _merge(src: Path, dst: Path) -> None:
    """Move the entries of folder `src` into folder `dst`, replacing same-named files."""
    for entry in src.iterdir():
        target = dst / entry.name
        if entry.is_dir() and target.is_dir():
            _merge(entry, target)
        else:
            if target.is_dir():
                shutil.rmtree(target)
            os.replace(entry, target)


@contextlib.contextmanager
def new_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Yields a temporary folder beside `path` to fill; on success it becomes `path` (or,
    with `path` already there after `check(..., force=True)`, its files replace the
    same-named ones in it); on failure it is removed and `path` is untouched."""
    path = Path(path)
    tmp = _tmp_name(path)
    _remove(tmp)
    tmp.mkdir()
    try:
        yield tmp
        if path.is_dir():
            _merge(tmp, path)
        else:
            os.replace(tmp, path)
    finally:
        _remove(tmp)


def write_text(path: str | os.PathLike | None, text: str) -> None:
    """Write `text` to `path` through `new_file` (``-``: stdout; None: nothing)."""
    if path is None:
        return
    if str(path) == "-":
        print(text)
        return
    with new_file(path) as tmp:
        tmp.write_text(text)


def write_json(path: str | os.PathLike | None, doc: Any, indent: int = 2) -> None:
    """`doc` as strict JSON (NaN becomes null) through `write_text`."""
    if path is not None:
        write_text(path, json.dumps(_finite(doc), indent=indent, allow_nan=False))


def _finite(x: Any) -> Any:
    """`x` with NaN and ±inf floats replaced by None (JSON null), numpy scalars as Python."""
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if hasattr(x, "tolist") and not isinstance(x, (str, bytes)):
        return _finite(x.tolist())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
