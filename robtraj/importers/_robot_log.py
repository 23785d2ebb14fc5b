"""A robot controller's joint log: UR RTDE CSV, any CSV with a JSON mapping, ROS 1/2 bags.

`read_joint_log` returns a `JointLog` on the log's own clock (the clock offset to the
tracker is estimated later, DESIGN section 5). Formats (docs/import.md, "Robot joint
logs"):

- ``ur-rtde``: the CSV that Universal Robots' RTDE recorder (``record_data.py``) or
  ``ur_rtde`` writes: space- or comma-separated, ``timestamp`` [s], ``actual_q_0`` …
  ``actual_q_5`` [rad], optionally ``target_q_0`` … ``target_q_5`` (commanded).
- ``csv``: any CSV with a JSON *mapping* (a file or a dict)::

      {"time": "t_ms", "time_unit": "ms", "joints": ["A1", "A2", "A3", "A4", "A5", "A6"],
       "commanded": ["C1", ..], "unit": "deg", "delimiter": ";", "decimal": ",",
       "skip_rows": 0, "names": ["a1", ..]}

  ``time`` (column, required); ``time_unit`` ``s`` (default), ``ms``, ``us`` or ``ns``;
  ``time_format`` ``number`` (default) or ``iso8601`` (e.g. ``2024-03-01T12:00:00.125Z``
  → seconds since the UNIX epoch, a time without UTC offset is read as UTC);
  ``joints`` (columns in joint order, required); ``commanded`` (as many columns,
  optional); ``unit`` ``rad`` (default) or ``deg`` for both; ``delimiter`` (default
  ``,``; ``" "`` or ``"whitespace"``: runs of blanks); ``decimal`` ``.`` (default) or
  ``,``; ``skip_rows`` lines before the header row (default 0); ``names`` joint names
  (default: the ``joints`` column names). Covers KUKA RSI and ABB signal-log exports.
- ``ros1`` / ``ros2``: ``sensor_msgs/JointState`` messages in a bag, read with rosbags
  (no ROS install). Time is the header stamp; only if every stamp is zero the bag's
  receive time (said in `JointLog.source`). Joints are picked by name. A second
  JointState topic whose name holds ``command`` or ``desired`` gives `commanded`,
  interpolated linearly onto `time` (NaN outside its time span).

Bad input is a one-line `UserError`. Samples are put in time order as follows: a CSV
whose time decreases is refused (the line is named: a log that goes back is usually
a clock reset or two logs in one file); bag messages are sorted by their stamp
(arrival order need not be stamp order). In both, exact repeats (same time, same
values) are dropped and a repeated time with other values is refused; what was done is
said in `JointLog.source`.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import UserError
from ._common import UR_JOINTS

JOINT_LOG_FORMATS = ("ur-rtde", "csv", "ros1", "ros2")

_TIME_UNITS = {"s": 1.0, "ms": 1e3, "us": 1e6, "ns": 1e9}
_ANGLE_UNITS = {"rad": 1.0, "deg": np.pi / 180}
_MAPPING_KEYS = {
    "time",
    "time_unit",
    "time_format",
    "joints",
    "commanded",
    "unit",
    "delimiter",
    "decimal",
    "skip_rows",
    "names",
}
_JOINT_STATE = {"sensor_msgs/msg/JointState", "sensor_msgs/JointState"}


@dataclasses.dataclass(frozen=True)
class JointLog:
    """A controller's joint log on its own clock.

    `time` `(K,)` [s, the log's own clock and epoch, strictly increasing]; `joints`
    `(K, J)` [rad] measured (actual) joint angles; `commanded` `(K, J)` [rad] or None;
    `names` the J joint names in column order; `source` the format and what the reader
    did (e.g. ``"ros2 bag, topic /joint_states, header stamps; dropped 2 repeated
    samples"``).
    """

    time: np.ndarray
    joints: np.ndarray
    commanded: np.ndarray | None
    names: tuple[str, ...]
    source: str


def guess_joint_log_format(path: str | os.PathLike, mapping: Any = None) -> str:
    """The format of `path`: ``.bag`` → ros1; a folder with ``metadata.yaml``, ``.mcap``
    or ``.db3`` → ros2; a CSV whose header has ``actual_q_0`` → ur-rtde (unless a
    `mapping` is given); another text file with a `mapping` → csv."""
    path = Path(path)
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return "ros2"
        raise UserError(f"{path}: a folder but not a ROS 2 bag (no metadata.yaml)")
    suffix = path.suffix.lower()
    if suffix == ".bag":
        return "ros1"
    if suffix in (".mcap", ".db3"):
        return "ros2"
    if mapping is not None:
        return "csv"
    if "actual_q_0" in _split(_first_line(path), _sniff(_first_line(path))):
        return "ur-rtde"
    raise UserError(
        f"{path}: not a UR RTDE log (no actual_q_0 column) nor a ROS bag; "
        "give a column mapping for a generic CSV joint log"
    )


def read_joint_log(
    path: str | os.PathLike,
    *,
    format: str | None = None,
    mapping: str | os.PathLike | Mapping[str, Any] | None = None,
    joint_names: Sequence[str] | None = None,
    topic: str | None = None,
) -> JointLog:
    """Read a robot controller's joint log.

    **Arguments:**

    - `path`: the log: a CSV file, a ROS 1 ``.bag``, a ROS 2 bag folder or its
      ``.mcap``/``.db3`` file.
    - `format`: ``"ur-rtde"``, ``"csv"``, ``"ros1"`` or ``"ros2"``; None guesses it
      (`guess_joint_log_format`).
    - `mapping`: for ``csv``: a JSON file or dict with the keys ``time``, ``time_unit``,
      ``time_format``, ``joints``, ``commanded``, ``unit``, ``delimiter``, ``decimal``,
      ``skip_rows``, ``names`` (module docstring; docs/import.md).
    - `joint_names`: bags: the joints to read, in this order (default: the names of the
      first message); CSV: names for the joint columns (as many as there are).
    - `topic`: bags: the JointState topic (default: the only one, not counting a
      ``command``/``desired`` topic).

    **Returns:** a `JointLog` with strictly increasing `time`.

    Bad input raises `UserError` with a one-line message. The joint count is not checked
    against a robot model here; the caller does that.
    """
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file or folder")
    fmt = format if format is not None else guess_joint_log_format(path, mapping)
    if fmt not in JOINT_LOG_FORMATS:
        raise UserError(f"unknown joint log format {fmt!r} (known: {', '.join(JOINT_LOG_FORMATS)})")
    if fmt in ("ros1", "ros2"):
        if mapping is not None:
            raise UserError("a column mapping applies to CSV joint logs, not to ROS bags")
        return _read_bag(path, fmt, topic, joint_names)
    if topic is not None:
        raise UserError("a topic applies to ROS bags, not to CSV joint logs")
    if fmt == "ur-rtde":
        if mapping is not None:
            raise UserError("ur-rtde logs need no mapping; use format 'csv' for a mapping")
        log = _read_rtde(path)
    else:
        if mapping is None:
            raise UserError(f"{path}: a generic CSV joint log needs a column mapping")
        log = _read_mapped_csv(path, _load_mapping(mapping))
    if joint_names is not None:
        names = tuple(str(n) for n in joint_names)
        if len(names) != len(log.names):
            raise UserError(
                f"{path}: {len(names)} joint names given for {len(log.names)} joint columns"
            )
        log = dataclasses.replace(log, names=names)
    return log


# ---------------------------------------------------------------- CSV


def _first_line(path: Path) -> str:
    try:
        with path.open(encoding="utf-8-sig") as f:
            for line in f:
                if line.strip():
                    return line
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: cannot read as text ({e})") from None
    return ""


def _sniff(header: str) -> str | None:
    for delimiter in (",", ";", "\t"):
        if delimiter in header:
            return delimiter
    return None  # runs of blanks


def _split(line: str, delimiter: str | None) -> list[str]:
    return [c.strip().strip('"').strip() for c in line.split(delimiter)]


class _Csv:
    """A header row and data lines (with their 1-based line numbers in the file)."""

    def __init__(self, path: Path, delimiter: str | None, decimal: str, skip_rows: int) -> None:
        try:
            all_lines = path.read_text(encoding="utf-8-sig").splitlines()
        except (OSError, UnicodeDecodeError) as e:
            raise UserError(f"{path}: cannot read as text ({e})") from None
        numbered = [(i + 1, ln) for i, ln in enumerate(all_lines[skip_rows:], skip_rows)]
        numbered = [(i, ln) for i, ln in numbered if ln.strip()]
        if not numbered:
            raise UserError(f"{path}: no header row")
        self.path, self.delimiter, self.decimal = path, delimiter, decimal
        self.header = _split(numbered[0][1], delimiter)
        self.lines = [ln for _, ln in numbered[1:]]
        self.line_numbers = np.array([i for i, _ in numbered[1:]], dtype=np.int64)
        if len(self.lines) < 2:
            raise UserError(f"{path}: {len(self.lines)} data rows; a joint log needs at least 2")

    def index(self, columns: Sequence[str], what: str) -> list[int]:
        missing = [c for c in columns if c not in self.header]
        if missing:
            raise UserError(
                f"{self.path}: no {what} column {', '.join(map(repr, missing))} "
                f"(columns: {', '.join(self.header)})"
            )
        return [self.header.index(c) for c in columns]

    def numbers(self, columns: Sequence[str], what: str) -> np.ndarray:
        """`(K, len(columns))` floats; a cell that is not a finite number names its line."""
        idx = self.index(columns, what)
        lines = self.lines
        if self.decimal != ".":
            lines = [ln.replace(self.decimal, ".") for ln in lines]
        quote = {} if self.delimiter is None else {"quotechar": '"'}
        try:
            out = np.loadtxt(
                lines, delimiter=self.delimiter, usecols=idx, ndmin=2, comments=None, **quote
            )
        except ValueError:
            self._find_bad_cell(lines, idx)
            raise  # not reached: _find_bad_cell raises
        bad = ~np.isfinite(out)
        if np.any(bad):
            i, j = np.argwhere(bad)[0]
            raise UserError(
                f"{self.path}: line {self.line_numbers[i]}, column {columns[j]!r}: "
                f"{out[i, j]} is not a finite number"
            )
        return out

    def _find_bad_cell(self, lines: list[str], idx: list[int]) -> None:
        for i, line in enumerate(lines):
            cells = _split(line, self.delimiter)
            for k in idx:
                where = f"{self.path}: line {self.line_numbers[i]}"
                if k >= len(cells):
                    raise UserError(
                        f"{where} has {len(cells)} fields, the header {len(self.header)}"
                    )
                try:
                    float(cells[k])
                except ValueError:
                    raise UserError(
                        f"{where}, column {self.header[k]!r}: {cells[k]!r} is not a number"
                    ) from None
        raise UserError(f"{self.path}: cannot read the columns as numbers")

    def strings(self, column: str, what: str) -> list[str]:
        (k,) = self.index([column], what)
        out = []
        for i, line in enumerate(self.lines):
            cells = _split(line, self.delimiter)
            if k >= len(cells):
                raise UserError(
                    f"{self.path}: line {self.line_numbers[i]} has {len(cells)} fields, "
                    f"the header {len(self.header)}"
                )
            out.append(cells[k])
        return out


def _read_rtde(path: Path) -> JointLog:
    table = _Csv(path, _sniff(_first_line(path)), ".", 0)
    if "timestamp" not in table.header:
        raise UserError(f"{path}: no 'timestamp' column (columns: {', '.join(table.header)})")
    actual = [f"actual_q_{i}" for i in range(6)]
    joints = table.numbers(actual, "joint")
    commanded = None
    target = [f"target_q_{i}" for i in range(6)]
    if any(c in table.header for c in target):
        commanded = table.numbers(target, "commanded joint")
    time = table.numbers(["timestamp"], "time")[:, 0]
    return _in_order(time, joints, commanded, UR_JOINTS, "ur-rtde", table.line_numbers, path)


def _load_mapping(mapping: str | os.PathLike | Mapping[str, Any]) -> dict[str, Any]:
    if isinstance(mapping, Mapping):
        doc, where = dict(mapping), "mapping"
    else:
        where = str(mapping)
        try:
            doc = json.loads(Path(mapping).read_text(encoding="utf-8-sig"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise UserError(f"{where}: not a readable JSON mapping ({e})") from None
        if not isinstance(doc, dict):
            raise UserError(f"{where}: a mapping file holds one JSON object")
    unknown = sorted(set(doc) - _MAPPING_KEYS)
    if unknown:
        raise UserError(
            f"{where}: unknown key {unknown[0]!r} (keys: {', '.join(sorted(_MAPPING_KEYS))})"
        )
    for key in ("time", "joints"):
        if key not in doc:
            raise UserError(
                f"{where}: lacks the key {key!r} (a joint log mapping needs 'time' and 'joints')"
            )
    if not isinstance(doc["time"], str):
        raise UserError(f"{where}: 'time' must name one column")
    for key in ("joints", "commanded", "names"):
        cols = doc.get(key, [])
        if not (isinstance(cols, list) and all(isinstance(c, str) for c in cols)):
            raise UserError(f"{where}: {key!r} must be a list of column names")
        if key != "joints" and key in doc and len(cols) != len(doc["joints"]):
            raise UserError(
                f"{where}: {key!r} has {len(cols)} entries, 'joints' {len(doc['joints'])}"
            )
    if not doc["joints"]:
        raise UserError(f"{where}: 'joints' names no column")
    choices = {
        "time_unit": _TIME_UNITS,
        "unit": _ANGLE_UNITS,
        "time_format": ("number", "iso8601"),
        "decimal": (".", ","),
    }
    for key, allowed in choices.items():
        if key in doc and doc[key] not in allowed:
            raise UserError(f"{where}: {key} {doc[key]!r} is not one of {', '.join(allowed)}")
    delimiter = doc.get("delimiter", ",")
    if not (isinstance(delimiter, str) and (len(delimiter) == 1 or delimiter == "whitespace")):
        raise UserError(f"{where}: delimiter {delimiter!r} is not one character or 'whitespace'")
    if delimiter == doc.get("decimal", "."):
        raise UserError(f"{where}: delimiter and decimal mark are both {delimiter!r}")
    skip = doc.get("skip_rows", 0)
    if not (isinstance(skip, int) and skip >= 0):
        raise UserError(f"{where}: skip_rows {skip!r} is not a non-negative integer")
    return doc


def _read_mapped_csv(path: Path, m: dict[str, Any]) -> JointLog:
    delimiter = m.get("delimiter", ",")
    table = _Csv(
        path,
        None if delimiter in (" ", "whitespace") else delimiter,
        m.get("decimal", "."),
        m.get("skip_rows", 0),
    )
    if m["time"] not in table.header:
        raise UserError(
            f"{path}: no time column {m['time']!r} (columns: {', '.join(table.header)})"
        )
    scale = _ANGLE_UNITS[m.get("unit", "rad")]
    joints = table.numbers(m["joints"], "joint") * scale
    commanded = (
        table.numbers(m["commanded"], "commanded joint") * scale if m.get("commanded") else None
    )
    if m.get("time_format", "number") == "iso8601":
        time = _iso_seconds(table.strings(m["time"], "time"), table.line_numbers, path)
    else:
        time = table.numbers([m["time"]], "time")[:, 0] / _TIME_UNITS[m.get("time_unit", "s")]
    names = tuple(m.get("names") or m["joints"])
    return _in_order(time, joints, commanded, names, "csv", table.line_numbers, path)


_EPOCH = datetime.datetime(1970, 1, 1, tzinfo=datetime.UTC)
_FRACTION = re.compile(r"^(.*\d\d:?\d\d:?\d\d)[.,](\d+)(.*)$")


def _iso_seconds(cells: list[str], line_numbers: np.ndarray, path: Path) -> np.ndarray:
    """ISO 8601 times → seconds since the UNIX epoch (no UTC offset: UTC), all digits of
    the fraction kept (``datetime`` alone stops at microseconds)."""
    out = np.empty(len(cells))
    for i, cell in enumerate(cells):
        text, fraction = cell, 0.0
        match = _FRACTION.match(cell)
        if match:
            text = match.group(1) + match.group(3)
            fraction = float("0." + match.group(2))
        try:
            stamp = datetime.datetime.fromisoformat(text)
        except ValueError:
            raise UserError(
                f"{path}: line {line_numbers[i]}: {cell!r} is not an ISO 8601 time"
            ) from None
        if stamp.tzinfo is None:
            stamp = stamp.replace(tzinfo=datetime.UTC)
        delta = stamp - _EPOCH
        out[i] = (delta.days * 86400 + delta.seconds) + (delta.microseconds * 1e-6 + fraction)
    return out


# ---------------------------------------------------------------- ordering


def _in_order(
    time: np.ndarray,
    joints: np.ndarray,
    commanded: np.ndarray | None,
    names: Sequence[str],
    source: str,
    line_numbers: np.ndarray,
    path: Path,
) -> JointLog:
    """A CSV's samples in strictly increasing time (exact repeats dropped)."""
    values = joints if commanded is None else np.concatenate([joints, commanded], axis=1)
    keep, notes = _tidy(time, time, values, line_numbers, path, sort=False, unit="line")
    return JointLog(
        time=time[keep],
        joints=joints[keep],
        commanded=None if commanded is None else commanded[keep],
        names=tuple(names),
        source="; ".join([source, *notes]),
    )


def _tidy(
    key: np.ndarray,
    seconds: np.ndarray,
    values: np.ndarray,
    labels: np.ndarray,
    path: Path,
    *,
    sort: bool,
    unit: str,
) -> tuple[np.ndarray, list[str]]:
    """Indices that put the samples in strictly increasing time, and what was done.

    `key` orders the samples (float seconds, or integer nanoseconds for bags: exact),
    `seconds` is the same time for messages. Sort (bags) or refuse a decrease (CSV);
    drop exact repeats (same time and `values`), refuse a repeated time with other values.
    """
    notes = []
    if not np.all(np.isfinite(seconds)):
        i = int(np.flatnonzero(~np.isfinite(seconds))[0])
        raise UserError(f"{path}: {unit} {labels[i]}: time {seconds[i]} is not a finite number")
    order = np.arange(key.size)
    if sort:
        order = np.argsort(key, kind="stable")
        moved = int(np.count_nonzero(order != np.arange(key.size)))
        if moved:
            notes.append(f"sorted {moved} {unit}s by time")
    else:
        back = np.flatnonzero(np.diff(key) < 0)
        if back.size:
            i = int(back[0]) + 1
            raise UserError(
                f"{path}: time goes back at {unit} {labels[i]} ({float(seconds[i])!r} s after "
                f"{float(seconds[i - 1])!r} s); a joint log's time must increase"
            )
    repeat = np.flatnonzero(np.diff(key[order]) == 0) + 1
    if repeat.size:
        now, before = values[order[repeat]], values[order[repeat - 1]]
        same = np.all((now == before) | (np.isnan(now) & np.isnan(before)), axis=1)
        if not np.all(same):
            i, j = order[repeat[~same][0]], order[repeat[~same][0] - 1]
            raise UserError(
                f"{path}: {unit} {labels[i]} repeats the time {float(seconds[i])!r} s of "
                f"{unit} {labels[j]} with other joint values"
            )
        order = np.delete(order, repeat)
        notes.append(f"dropped {repeat.size} repeated {unit}s (same time and values)")
    if order.size < 2:
        raise UserError(f"{path}: {order.size} distinct sample(s); a joint log needs at least 2")
    return order, notes


# ---------------------------------------------------------------- ROS bags


def _read_bag(
    path: Path, fmt: str, topic: str | None, joint_names: Sequence[str] | None
) -> JointLog:
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.typesys import Stores, get_typestore

    if (fmt == "ros1") != (path.suffix.lower() == ".bag"):
        want = "a .bag file" if fmt == "ros1" else "a bag folder, .mcap or .db3"
        raise UserError(f"{path}: a {fmt} joint log is {want}")
    try:
        # the typestore is used only for ROS 2 bags that carry no message definitions
        with AnyReader([path], default_typestore=get_typestore(Stores.LATEST)) as reader:
            states = [c for c in reader.connections if c.msgtype in _JOINT_STATE]
            topics = sorted({c.topic for c in states})
            if not topics:
                have = ", ".join(sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections}))
                raise UserError(
                    f"{path}: no sensor_msgs/JointState topic (topics: {have or 'none'})"
                )
            measured_topic = _measured_topic(path, topics, topic)
            commands = [t for t in topics if t != measured_topic and _is_command(t)]
            measured = _messages(reader, path, states, measured_topic, joint_names)
            names = measured[0]
            command = None
            if len(commands) == 1 and not _is_command(measured_topic):
                try:
                    command = _messages(reader, path, states, commands[0], names)
                except UserError as e:
                    command = str(e).removeprefix(f"{path}: ")
    except (AnyReaderError, Reader1Error, Reader2Error) as e:
        raise UserError(f"{path}: cannot read the bag ({e})") from None

    names, stamp_ns, receive_ns, positions, skipped = measured
    time_ns, clock = _clock(path, measured_topic, stamp_ns, receive_ns)
    notes = [f"{fmt} bag, topic {measured_topic}, {clock}"]
    if skipped:
        notes.append(f"skipped {skipped} messages without these joints")
    keep, done = _bag_order(path, time_ns, positions)
    notes += done
    time_ns, positions = time_ns[keep], positions[keep]
    commanded = None
    if isinstance(command, tuple):
        try:
            commanded = _interpolate(path, command, clock, time_ns)
            notes.append(f"commanded: {commands[0]}, interpolated")
        except UserError as e:
            command = str(e).removeprefix(f"{path}: ")
    if isinstance(command, str):
        notes.append(f"commanded topic {commands[0]} not used: {command}")
    elif len(commands) > 1:
        notes.append(f"commanded not read: several topics ({', '.join(commands)})")
    return JointLog(
        time=_seconds(time_ns),
        joints=positions,
        commanded=commanded,
        names=names,
        source="; ".join(notes),
    )


def _is_command(topic: str) -> bool:
    return "command" in topic.lower() or "desired" in topic.lower()


def _measured_topic(path: Path, topics: list[str], topic: str | None) -> str:
    if topic is not None:
        if topic not in topics:
            raise UserError(
                f"{path}: no JointState topic {topic!r} (JointState topics: {', '.join(topics)})"
            )
        return topic
    measured = [t for t in topics if not _is_command(t)] or topics
    if len(measured) > 1:
        raise UserError(
            f"{path}: several JointState topics ({', '.join(measured)}); choose one with the topic option"
        )
    return measured[0]


def _messages(
    reader: Any, path: Path, states: list[Any], topic: str, joint_names: Sequence[str] | None
) -> tuple[tuple[str, ...], np.ndarray, np.ndarray, np.ndarray, int]:
    """Names, header stamps [ns], receive times [ns], positions `(K, J)`, messages skipped."""
    names = None if joint_names is None else tuple(str(n) for n in joint_names)
    if names is not None and len(set(names)) != len(names):
        raise UserError(f"the joint names repeat a name: {', '.join(names)}")
    picks: dict[tuple[str, ...], np.ndarray | None] = {}
    stamps, receives, rows, skipped = [], [], [], 0
    connections = [c for c in states if c.topic == topic]
    for connection, receive_ns, raw in reader.messages(connections=connections):
        msg = reader.deserialize(raw, connection.msgtype)
        have = tuple(msg.name)
        if names is None:
            names = have
        if have not in picks:
            picks[have] = _pick(path, topic, have, names, len(rows) + skipped + 1)
        pick = picks[have]
        if pick is None:
            skipped += 1
            continue
        position = np.asarray(msg.position, dtype=np.float64)
        if position.shape != (len(have),):
            raise UserError(
                f"{path}: a message on {topic} has {len(have)} joint names but "
                f"{position.size} positions"
            )
        stamps.append(int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec))
        receives.append(receive_ns)
        rows.append(position[pick])
    if not rows:
        holds = f" holds the joints {', '.join(map(repr, names))}" if names else ""
        raise UserError(f"{path}: no message on {topic}{holds}")
    return (
        names,
        np.array(stamps, dtype=np.int64),
        np.array(receives, dtype=np.int64),
        np.array(rows),
        skipped,
    )


def _pick(
    path: Path, topic: str, have: tuple[str, ...], names: tuple[str, ...], number: int
) -> np.ndarray | None:
    """Indices of `names` in a message's `have` (None: it holds none of them)."""
    missing = [n for n in names if n not in have]
    if len(missing) == len(names):
        return None
    if missing:
        raise UserError(
            f"{path}: message {number} on {topic} lacks joint {', '.join(map(repr, missing))} "
            f"(it has {', '.join(have)})"
        )
    return np.array([have.index(n) for n in names], dtype=np.intp)


def _clock(
    path: Path, topic: str, stamp_ns: np.ndarray, receive_ns: np.ndarray
) -> tuple[np.ndarray, str]:
    zero = stamp_ns == 0
    if np.all(zero):
        return receive_ns, "receive time (header stamps are all zero)"
    if np.any(zero):
        raise UserError(
            f"{path}: {np.count_nonzero(zero)} of {zero.size} messages on {topic} have a zero "
            "header stamp"
        )
    return stamp_ns, "header stamps"


def _seconds(ns: np.ndarray) -> np.ndarray:
    whole, part = np.divmod(ns, 1_000_000_000)
    return whole.astype(np.float64) + part / 1e9


def _bag_order(path: Path, ns: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, list[str]]:
    labels = np.arange(1, ns.size + 1)
    return _tidy(ns, _seconds(ns), positions, labels, path, sort=True, unit="message")


def _interpolate(path: Path, command: tuple, clock: str, time_ns: np.ndarray) -> np.ndarray:
    """The command topic's joints, linear in time, at `time_ns`; NaN outside its span."""
    _, stamp_ns, receive_ns, positions, _ = command
    ns = receive_ns if clock.startswith("receive") else stamp_ns
    keep, _ = _bag_order(path, ns, positions)
    origin = time_ns[0]  # relative seconds: epoch seconds in float64 resolve only ~0.2 us
    x, xp = (time_ns - origin) / 1e9, (ns[keep] - origin) / 1e9
    return np.stack(
        [np.interp(x, xp, q, left=np.nan, right=np.nan) for q in positions[keep].T], axis=1
    )
