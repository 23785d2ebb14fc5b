"""The `Recording` type and the one HDF5 reader/writer for schema version 1 (DESIGN section 4).

Everything in SI: metres, radians, seconds. Quaternions are unit, in w, x, y, z order.
LED positions are in the camera (tracker) frame with NaN where an LED was not seen.

Raw data is never modified in place: `write_recording` refuses to overwrite an
existing file unless asked to, and writes through a temporary file that is renamed
into place only when complete. Groups, datasets and attributes the schema does not
know survive a read–write round trip (`Recording.extras`, `Recording.extra_attrs`).
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import zlib
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import h5py
import numpy as np

from ._errors import UserError

try:  # ISA-L's deflate: zlib streams as any inflater reads them, several times faster
    from isal import isal_zlib as _isal_zlib
except ImportError:  # a platform without isal: zlib (the recorder's writer then needs more CPU)
    _isal_zlib = None

SCHEMA = "robtraj.recording"
SCHEMA_VERSION = 1
_QUAT_TOL = 1e-6
_TRACKER_CHUNK_FRAMES = 1000
#: frames per HDF5 chunk of the per-frame datasets `write_recording` writes (fewer: all)
TRACKER_CHUNK_FRAMES = _TRACKER_CHUNK_FRAMES


class RecordingError(UserError):
    """A recording file that does not follow schema version 1; the message names the dataset."""


@dataclasses.dataclass(frozen=True)
class Pose:
    """Rigid pose(s): `position` `(..., 3)` [m] and unit `quaternion_wxyz` `(..., 4)`."""

    position: np.ndarray
    quaternion_wxyz: np.ndarray

    @classmethod
    def from_wxyz_xyz(cls, wxyz_xyz) -> Pose:
        """The pose(s) of jaxlie's ``wxyz_xyz`` layout `(..., 7)` (float64 copies)."""
        a = np.asarray(wxyz_xyz, np.float64)
        return cls(position=a[..., 4:].copy(), quaternion_wxyz=a[..., :4].copy())


@dataclasses.dataclass(frozen=True)
class RobotLog:
    """Robot controller log: `time` `(K,)` [s, robot clock], `joints` `(K, J)` [rad].

    Kinematics as a named built-in `model` (e.g. ``"abb_irb2400_16"``) or a standard-DH
    table `dh` `(J, 4)` with rows ``[d, a, alpha, theta_offset]`` [m, m, rad, rad].
    Optional: `flange`, the flange (tool0) frame in the last DH frame (a `Pose` of
    shape `()`), and `link_mass` `(J,)` [kg], the mass of each link for gravity torques;
    where given they replace the built-in model's (a DH table without them: identity
    flange, 5 kg per link); `payload_mass` [kg] at the flange likewise (default 1 kg);
    `joint_limits` `(J, 2)` [rad] each joint's range ``[lower, upper]`` (±inf: no limit
    on that side) likewise (a DH table without them: unlimited).

    A log joined to a tracker stream (`robtraj attach`) has been moved onto the tracker
    clock: `time` is the controller's clock minus `clock_offset` [s], found from the data
    with standard error `clock_offset_sigma` [s] (0 where the user gave the offset; None
    for a log never aligned). The calibration's τ then refines what is left.
    """

    time: np.ndarray
    joints: np.ndarray
    model: str | None = None
    dh: np.ndarray | None = None
    flange: Pose | None = None
    link_mass: np.ndarray | None = None
    payload_mass: float | None = None
    clock_offset: float = 0.0
    clock_offset_sigma: float | None = None
    joint_limits: np.ndarray | None = None

    def model_document(self) -> dict[str, Any]:
        """The robot model alone as the DH JSON document of docs/import.md (metres,
        radians): ``{"model": name}`` for a built-in, else ``{"name", "dh", "flange",
        "link_mass", "payload_mass", "joint_limits"}`` with what is given (an infinite
        limit as null)."""
        if self.dh is None:
            return {"model": self.model}
        doc: dict[str, Any] = {"name": self.model or "custom", "unit": "m", "angle_unit": "rad"}
        doc["dh"] = np.asarray(self.dh, np.float64).tolist()
        if self.flange is not None:
            doc["flange"] = {
                "position": np.asarray(self.flange.position, np.float64).tolist(),
                "quaternion_wxyz": np.asarray(self.flange.quaternion_wxyz, np.float64).tolist(),
            }
        if self.link_mass is not None:
            doc["link_mass"] = np.asarray(self.link_mass, np.float64).tolist()
        if self.payload_mass is not None:
            doc["payload_mass"] = float(self.payload_mass)
        if self.joint_limits is not None:
            doc["joint_limits"] = limits_document(self.joint_limits)
        return doc


def limits_document(limits: np.ndarray, scale: float = 1.0) -> list[list[float | None]]:
    """Joint limits `(J, 2)` [rad] as JSON rows ``[lower, upper]`` divided by `scale`,
    an infinite limit (none on that side) as None."""
    rows = np.asarray(limits, np.float64) / scale
    return [[float(v) if np.isfinite(v) else None for v in row] for row in rows]


@dataclasses.dataclass(frozen=True)
class Program:
    """Commanded program: TCP `targets` (a `Pose` with `(P, ·)` arrays) in the base frame.

    `motion` `(P,)` is ``"start"``, ``"linear"`` or ``"joint"``; `speed` `(P,)` [m/s] is the
    commanded TCP speed to each target; `segment` `(N,)` optionally gives the program
    segment index of each tracker frame.
    """

    targets: Pose
    motion: np.ndarray
    speed: np.ndarray
    segment: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class Tool:
    """The LED tool: nominal `constellation` `(M, 3)` [m] in the tool frame, per `led_ids`.

    `normals` `(M, 3)` are unit LED emission axes in the tool frame (optional),
    `reference_leds` `(3,)` the ids of the three reference LEDs, `flange_from_tool` the
    nominal TCP (optional).
    """

    led_ids: np.ndarray
    constellation: np.ndarray
    normals: np.ndarray | None = None
    reference_leds: np.ndarray | None = None
    flange_from_tool: Pose | None = None


@dataclasses.dataclass(frozen=True)
class Probe:
    """Tool frame probed in the camera frame at static robot poses: `time` `(S,)`, `tool_pose`."""

    time: np.ndarray
    tool_pose: Pose


@dataclasses.dataclass(frozen=True)
class Truth:
    """Simulation ground truth, never read by estimation code.

    `tool_pose` `(N, ·)` is the true tool pose in the camera frame per tracker frame.
    `effects` maps effect names to their hidden parameter values (JSON-able).
    """

    tool_pose: Pose
    camera_from_base: Pose
    flange_from_tool: Pose
    constellation: np.ndarray
    effects: dict[str, Any] = dataclasses.field(default_factory=dict)


@runtime_checkable
class FrameArray(Protocol):
    """A per-frame array as the passes over a recording read it: `shape`, `dtype` and
    ``x[a:b]`` giving frames ``a..b-1`` as a NumPy array. A NumPy array is one (its slices
    are free); so are the lazily read datasets of `robtraj.open_recording`."""

    shape: tuple[int, ...]
    dtype: Any

    def __getitem__(self, key: Any) -> Any: ...


def finite_points(points: np.ndarray) -> np.ndarray:
    """`(...)` bool: all three coordinates of each point `(..., 3)` finite (as
    ``np.all(np.isfinite(points), -1)``, a coordinate at a time: a reduction over an axis
    of length 3 is slow in NumPy)."""
    return np.isfinite(points[..., 0]) & np.isfinite(points[..., 1]) & np.isfinite(points[..., 2])


@dataclasses.dataclass(frozen=True)
class Recording:
    """One tracker recording (DESIGN section 4), all arrays NumPy, SI units.

    `positions` `(N, M, 3)` are LED positions in the camera frame [m], NaN where unseen;
    `time` `(N,)` the strictly increasing tracker clock [s]; `frame_index` `(N,)` the
    unwrapped device frame counter (gaps are lost frames); `led_ids` `(M,)`.
    """

    time: np.ndarray
    frame_index: np.ndarray
    led_ids: np.ndarray
    positions: np.ndarray | FrameArray  # read by frame ranges when opened lazily
    status: np.ndarray | FrameArray | None = None
    temperature: np.ndarray | None = None
    robot: RobotLog | None = None
    program: Program | None = None
    tool: Tool | None = None
    probe: Probe | None = None
    truth: Truth | None = None
    attrs: dict[str, Any] = dataclasses.field(default_factory=dict)
    extras: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    extra_attrs: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.time.shape[0])

    @property
    def n_leds(self) -> int:
        return int(self.led_ids.shape[0])

    @property
    def visible(self) -> np.ndarray:
        """`(N, M)` bool: LED seen in that frame (all three coordinates finite)."""
        return finite_points(self.positions)

    def replace(self, **changes: Any) -> Recording:
        return dataclasses.replace(self, **changes)


# ----------------------------------------------------------------------------- writing


def _create(group: h5py.Group, name: str, data: Any, *, time_chunked: bool = False) -> None:
    data = np.asarray(data)
    if data.dtype.kind == "U":
        group.create_dataset(name, data=data.astype(object), dtype=h5py.string_dtype())
        return
    if time_chunked and data.ndim >= 1 and data.shape[0] > 0:
        chunks = (min(_TRACKER_CHUNK_FRAMES, data.shape[0]), *data.shape[1:])
        group.create_dataset(
            name,
            data=data,
            chunks=chunks,
            maxshape=(None, *data.shape[1:]),
            compression="gzip",
            compression_opts=1,
            shuffle=True,
        )
    else:
        group.create_dataset(name, data=data)


def _write_pose(group: h5py.Group, name: str, pose: Pose, *, time_chunked: bool = False) -> None:
    g = group.create_group(name)
    _create(g, "position", np.asarray(pose.position, np.float64), time_chunked=time_chunked)
    _create(
        g,
        "quaternion_wxyz",
        np.asarray(pose.quaternion_wxyz, np.float64),
        time_chunked=time_chunked,
    )


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


def write_recording(rec: Recording, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Write `rec` to `path` as schema-1 HDF5; returns the path.

    Refuses (`UserError`) to replace an existing file unless `overwrite`. The file is
    written under a temporary name next to `path` and renamed into place when complete,
    so a failure never leaves a half-written file under the final name.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise UserError(f"{path} exists; refusing to overwrite it (use --force or another name)")
    _validate(rec, str(path))
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with h5py.File(tmp, "w") as f:
            _write_into(f, rec)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _write_into(f: h5py.File, rec: Recording) -> None:
    attrs = {
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "source": "simulation",
        **rec.attrs,
    }
    attrs["schema"] = SCHEMA
    attrs["schema_version"] = SCHEMA_VERSION
    for k, v in attrs.items():
        f.attrs[k] = v

    t = f.create_group("tracker")
    _create(t, "time", np.asarray(rec.time, np.float64), time_chunked=True)
    _create(t, "frame_index", np.asarray(rec.frame_index, np.uint64), time_chunked=True)
    _create(t, "led_ids", np.asarray(rec.led_ids, np.int32))
    _create(t, "positions", np.asarray(rec.positions, np.float64), time_chunked=True)
    if rec.status is not None:
        _create(t, "status", np.asarray(rec.status, np.uint8), time_chunked=True)
    if rec.temperature is not None:
        _create(t, "temperature", np.asarray(rec.temperature, np.float32), time_chunked=True)

    if rec.robot is not None:
        r = f.create_group("robot")
        _create(r, "time", np.asarray(rec.robot.time, np.float64), time_chunked=True)
        _create(r, "joints", np.asarray(rec.robot.joints, np.float64), time_chunked=True)
        if rec.robot.model is not None:
            r.attrs["model"] = rec.robot.model
        if rec.robot.payload_mass is not None:
            r.attrs["payload_mass_kg"] = float(rec.robot.payload_mass)
        if rec.robot.clock_offset_sigma is not None:
            r.attrs["clock_offset_s"] = float(rec.robot.clock_offset)
            r.attrs["clock_offset_sigma_s"] = float(rec.robot.clock_offset_sigma)
        if rec.robot.dh is not None:
            _create(r, "dh", np.asarray(rec.robot.dh, np.float64))
        if rec.robot.flange is not None:
            _write_pose(r, "flange", rec.robot.flange)
        if rec.robot.link_mass is not None:
            _create(r, "link_mass", np.asarray(rec.robot.link_mass, np.float64))
        if rec.robot.joint_limits is not None:
            _create(r, "joint_limits", np.asarray(rec.robot.joint_limits, np.float64))

    if rec.program is not None:
        p = f.create_group("program")
        _write_pose(p, "targets", rec.program.targets)
        _create(p, "motion", np.asarray(rec.program.motion, dtype=str))
        _create(p, "speed", np.asarray(rec.program.speed, np.float64))
        if rec.program.segment is not None:
            _create(p, "segment", np.asarray(rec.program.segment, np.int32), time_chunked=True)

    if rec.tool is not None:
        g = f.create_group("tool")
        _create(g, "led_ids", np.asarray(rec.tool.led_ids, np.int32))
        _create(g, "constellation", np.asarray(rec.tool.constellation, np.float64))
        if rec.tool.normals is not None:
            _create(g, "normals", np.asarray(rec.tool.normals, np.float64))
        if rec.tool.reference_leds is not None:
            _create(g, "reference_leds", np.asarray(rec.tool.reference_leds, np.int32))
        if rec.tool.flange_from_tool is not None:
            _write_pose(g, "flange_from_tool", rec.tool.flange_from_tool)

    if rec.probe is not None:
        g = f.create_group("probe")
        _create(g, "time", np.asarray(rec.probe.time, np.float64))
        _write_pose(g, "tool_pose", rec.probe.tool_pose)

    if rec.truth is not None:
        g = f.create_group("truth")
        _write_pose(g, "tool_pose", rec.truth.tool_pose, time_chunked=True)
        _write_pose(g, "camera_from_base", rec.truth.camera_from_base)
        _write_pose(g, "flange_from_tool", rec.truth.flange_from_tool)
        _create(g, "constellation", np.asarray(rec.truth.constellation, np.float64))
        g.attrs["effects"] = json.dumps(_jsonable(rec.truth.effects))

    for name, data in rec.extras.items():
        parent, _, leaf = name.rpartition("/")
        group = f.require_group(parent) if parent else f
        _create(group, leaf, data)
    for name, extra in rec.extra_attrs.items():
        obj = f[name] if name in f else f.require_group(name)
        for k, v in extra.items():
            obj.attrs[k] = v


# ----------------------------------------------------------------------------- reading

_KNOWN_ATTRS = {
    "/": {"schema", "schema_version", "created", "source"},
    "/robot": {"model", "payload_mass_kg", "clock_offset_s", "clock_offset_sigma_s"},
    "/truth": {"effects"},
}


def read_recording(path: str | os.PathLike) -> Recording:
    """Read and validate a schema-1 recording.

    Raises `RecordingError` with a message naming the offending dataset for a wrong
    `schema`, a newer `schema_version`, a missing required dataset, a shape mismatch,
    non-increasing time or a non-unit quaternion; `UserError` if the file is missing
    or not HDF5.

    A recording that a recorder (`RecordingAppender`) was writing when it was killed is
    read up to its last complete frame (see `_trim_interrupted_flush`).
    """
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file")
    name = str(path)
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        try:  # a SWMR writer killed (robtraj's earlier recorders) leaves its flag set
            f = h5py.File(path, "r", swmr=True)
        except OSError:
            raise UserError(f"{path}: not a readable HDF5 file ({e})") from None
    try:
        with f:
            rec = _read_file(f, name)
    except OSError:
        # a recorder killed while flushing: chunks indexed beyond the end-of-file address
        # in the superblock, which is written last; SWMR reading does not check reads
        # against that address
        try:
            with h5py.File(path, "r", swmr=True) as f:
                rec = _read_file(f, name)
        except OSError as e:
            raise UserError(f"{path}: unreadable HDF5 data ({e})") from None
    _validate(rec, name)
    return rec


#: the per-frame tracker datasets `read_deferred` can leave in the file
DEFERRABLE = {"positions": "/tracker/positions", "status": "/tracker/status"}


def read_deferred(
    f: h5py.File,
    name: str,
    wrap: Mapping[str, Callable[[h5py.Dataset, int], Any]],
    *,
    truth: bool = True,
) -> Recording:
    """The recording in the open file `f`, read and checked as `read_recording` does,
    except the per-frame datasets named in `wrap` (keys of `DEFERRABLE`): each is left in
    the file, its shape checked without reading it, and replaced by
    ``wrap[key](dataset, n_frames)`` (e.g. an array read on demand,
    `robtraj.open_recording`). `name` names the file in messages. Without `truth` a
    simulation's /truth is left unread (``truth=None``). Raises `OSError` where HDF5
    cannot read the rest."""
    defer = frozenset(DEFERRABLE[k] for k in wrap) | (frozenset() if truth else {"/truth"})
    rec = _read_file(f, name, defer)
    datasets = {k: getattr(rec, k) for k in wrap if getattr(rec, k) is not None}
    for k, ds in datasets.items():
        if ds.dtype.kind not in "fiub":
            raise RecordingError(f"{name}: {DEFERRABLE[k]} must be numeric, not {ds.dtype}")
    # shapes only (arrays that take no memory): the trimming and the checks of a full read
    placeholders = {k: np.broadcast_to(np.zeros((), d.dtype), d.shape) for k, d in datasets.items()}
    shaped = _trim_interrupted_flush(rec.replace(**placeholders))
    _validate(shaped, name)
    return shaped.replace(
        **{k: wrap[k](d, getattr(shaped, k).shape[0]) for k, d in datasets.items()}
    )


def _read_file(f: h5py.File, name: str, defer: frozenset[str] = frozenset()) -> Recording:
    """The checked schema's recording in `f`; with `defer` (see `_read_from`) untrimmed:
    the caller applies `_trim_interrupted_flush`."""
    schema = f.attrs.get("schema")
    if isinstance(schema, bytes):
        schema = schema.decode()
    if schema != SCHEMA:
        raise RecordingError(f"{name}: attribute /schema is {schema!r}, expected {SCHEMA!r}")
    version = f.attrs.get("schema_version")
    try:
        version = int(version)
    except (TypeError, ValueError):
        raise RecordingError(f"{name}: attribute /schema_version is missing or not an integer")
    if version > SCHEMA_VERSION:
        raise RecordingError(
            f"{name}: /schema_version is {version}, newer than this robtraj reads "
            f"({SCHEMA_VERSION}); upgrade robtraj"
        )
    used: set[str] = set()
    rec = _read_from(f, name, used, defer)
    return rec if defer else _trim_interrupted_flush(rec)


def _trim_interrupted_flush(rec: Recording) -> Recording:
    """The complete frames of a recorder's file (``source="device"``) killed mid-flush.

    `RecordingAppender` writes its datasets one after the other, /tracker/time last, and
    a dataset's new extent may reach the disk before its chunks are indexed: then the
    datasets differ in length, and /tracker/time ends with frames that read as its fill
    value or the padding of its last chunk, NaN. Those frames, and every dataset's frames
    beyond the shortest one, are dropped; the frames left are complete in every dataset.
    Any other file is returned as read (and a NaN time fails validation).
    """
    if rec.attrs.get("source") != "device" or np.ndim(rec.time) != 1:
        return rec
    keys = ("time", "frame_index", "positions", "status", "temperature")
    arrays = {k: getattr(rec, k) for k in keys if getattr(rec, k) is not None}
    if any(np.ndim(a) < 1 for a in arrays.values()):
        return rec
    n = min(a.shape[0] for a in arrays.values())
    timed = np.flatnonzero(~np.isnan(rec.time[:n]))
    n = int(timed[-1]) + 1 if timed.size else 0
    if all(a.shape[0] == n for a in arrays.values()):
        return rec
    return rec.replace(**{k: a[:n] for k, a in arrays.items()})


def _get(
    f: h5py.File,
    key: str,
    name: str,
    used: set[str],
    *,
    required: bool = True,
    defer: frozenset[str] = frozenset(),
) -> Any:
    if key not in f:
        if required:
            raise RecordingError(f"{name}: required dataset {key} is missing")
        return None
    obj = f[key]
    if not isinstance(obj, h5py.Dataset):
        raise RecordingError(f"{name}: {key} is a group, expected a dataset")
    used.add(key)
    if key in defer:  # left in the file: read on demand (`open_recording`)
        return obj
    data = obj[()]
    if obj.dtype.kind == "O" or h5py.check_string_dtype(obj.dtype) is not None:
        data = np.asarray([d.decode() if isinstance(d, bytes) else str(d) for d in np.ravel(data)])
    return data


def _get_pose(f: h5py.File, key: str, name: str, used: set[str], required: bool = True):
    pos = _get(f, f"{key}/position", name, used, required=required)
    quat = _get(f, f"{key}/quaternion_wxyz", name, used, required=required)
    if pos is None or quat is None:
        return None
    return Pose(np.asarray(pos, np.float64), np.asarray(quat, np.float64))


def _attr_str(obj: h5py.HLObject, key: str) -> str | None:
    v = obj.attrs.get(key)
    if v is None:
        return None
    return v.decode() if isinstance(v, bytes) else str(v)


def _read_from(
    f: h5py.File, name: str, used: set[str], defer: frozenset[str] = frozenset()
) -> Recording:
    """The recording in `f`; the datasets named in `defer` are returned unread (as
    `h5py.Dataset`s), and /truth is not read at all when `defer` names it."""
    g = lambda key, required=True: _get(f, key, name, used, required=required, defer=defer)  # noqa: E731
    robot = None
    if "robot" in f:
        robot = RobotLog(
            time=g("/robot/time"),
            joints=g("/robot/joints"),
            model=_attr_str(f["robot"], "model"),
            payload_mass=(
                float(f["robot"].attrs["payload_mass_kg"])
                if "payload_mass_kg" in f["robot"].attrs
                else None
            ),
            clock_offset=float(f["robot"].attrs.get("clock_offset_s", 0.0)),
            clock_offset_sigma=(
                float(f["robot"].attrs["clock_offset_sigma_s"])
                if "clock_offset_sigma_s" in f["robot"].attrs
                else None
            ),
            dh=g("/robot/dh", False),
            flange=_get_pose(f, "/robot/flange", name, used, required=False),
            link_mass=g("/robot/link_mass", False),
            joint_limits=g("/robot/joint_limits", False),
        )
    program = None
    if "program" in f:
        program = Program(
            targets=_get_pose(f, "/program/targets", name, used),
            motion=g("/program/motion"),
            speed=g("/program/speed"),
            segment=g("/program/segment", False),
        )
    tool = None
    if "tool" in f:
        tool = Tool(
            led_ids=g("/tool/led_ids"),
            constellation=g("/tool/constellation"),
            normals=g("/tool/normals", False),
            reference_leds=g("/tool/reference_leds", False),
            flange_from_tool=_get_pose(f, "/tool/flange_from_tool", name, used, required=False),
        )
    probe = None
    if "probe" in f:
        probe = Probe(time=g("/probe/time"), tool_pose=_get_pose(f, "/probe/tool_pose", name, used))
    truth = None
    if "truth" in f and "/truth" in defer:  # known, not read: no extras either
        f["truth"].visit(lambda key: used.add(f"/truth/{key}"))
    elif "truth" in f:
        effects_raw = _attr_str(f["truth"], "effects")
        truth = Truth(
            tool_pose=_get_pose(f, "/truth/tool_pose", name, used),
            camera_from_base=_get_pose(f, "/truth/camera_from_base", name, used),
            flange_from_tool=_get_pose(f, "/truth/flange_from_tool", name, used),
            constellation=g("/truth/constellation"),
            effects=json.loads(effects_raw) if effects_raw else {},
        )
    rec = Recording(
        time=g("/tracker/time"),
        frame_index=g("/tracker/frame_index"),
        led_ids=g("/tracker/led_ids"),
        positions=g("/tracker/positions"),
        status=g("/tracker/status", False),
        temperature=g("/tracker/temperature", False),
        robot=robot,
        program=program,
        tool=tool,
        probe=probe,
        truth=truth,
        attrs={k: _plain_attr(v) for k, v in f.attrs.items() if k in _KNOWN_ATTRS["/"]},
    )
    extras: dict[str, np.ndarray] = {}
    extra_attrs: dict[str, dict[str, Any]] = {}

    def visit(key: str, obj: h5py.HLObject) -> None:
        full = "/" + key
        if isinstance(obj, h5py.Dataset) and full not in used:
            extras[key] = obj[()]
        known = _KNOWN_ATTRS.get(full, set())
        rest = {k: _plain_attr(v) for k, v in obj.attrs.items() if k not in known}
        is_unknown_group = isinstance(obj, h5py.Group) and not _is_schema_group(full)
        if rest or (is_unknown_group and len(obj) == 0):
            extra_attrs[key] = rest

    f.visititems(visit)
    root_rest = {k: _plain_attr(v) for k, v in f.attrs.items() if k not in _KNOWN_ATTRS["/"]}
    return rec.replace(attrs={**rec.attrs, **root_rest}, extras=extras, extra_attrs=extra_attrs)


_SCHEMA_GROUPS = {
    "/tracker",
    "/robot",
    "/robot/flange",
    "/program",
    "/program/targets",
    "/tool",
    "/tool/flange_from_tool",
    "/probe",
    "/probe/tool_pose",
    "/truth",
    "/truth/tool_pose",
    "/truth/camera_from_base",
    "/truth/flange_from_tool",
}


def _is_schema_group(full: str) -> bool:
    return full in _SCHEMA_GROUPS


def _plain_attr(v: Any) -> Any:
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.generic):
        return v.item()
    return v


# ----------------------------------------------------------------------------- validation


def _check_shape(name: str, key: str, arr: np.ndarray, shape: tuple) -> None:
    arr = np.asarray(arr)
    ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape))
    if not ok:
        want = "(" + ", ".join("·" if s is None else str(s) for s in shape) + ")"
        raise RecordingError(f"{name}: {key} has shape {arr.shape}, expected {want}")


def _check_integer(name: str, key: str, arr: np.ndarray) -> None:
    if not np.issubdtype(np.asarray(arr).dtype, np.integer):
        raise RecordingError(
            f"{name}: {key} must hold integer LED ids, not {np.asarray(arr).dtype}"
        )


def _check_increasing(name: str, key: str, t: np.ndarray) -> None:
    t = np.asarray(t, np.float64)
    if not np.all(np.isfinite(t)):
        raise RecordingError(f"{name}: {key} contains NaN or infinite values")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise RecordingError(
            f"{name}: {key} is not strictly increasing (index {bad[0] + 1}: "
            f"{t[bad[0]]!r} then {t[bad[0] + 1]!r})"
        )


def _check_pose(name: str, key: str, pose: Pose, lead: tuple) -> None:
    _check_shape(name, f"{key}/position", pose.position, (*lead, 3))
    _check_shape(name, f"{key}/quaternion_wxyz", pose.quaternion_wxyz, (*lead, 4))
    q = np.asarray(pose.quaternion_wxyz, np.float64)
    norm = np.linalg.norm(q, axis=-1)
    finite = np.isfinite(norm)  # NaN poses (e.g. unseen frames) are allowed
    bad = np.flatnonzero(finite.ravel() & (np.abs(norm.ravel() - 1.0) > _QUAT_TOL))
    if bad.size:
        raise RecordingError(
            f"{name}: {key}/quaternion_wxyz is not unit (norm {norm.ravel()[bad[0]]:.9g} "
            f"at index {bad[0]})"
        )


def _validate(rec: Recording, name: str) -> None:
    n = rec.time.shape[0] if np.ndim(rec.time) == 1 else None
    _check_shape(name, "/tracker/time", rec.time, (None,))
    m = np.shape(rec.led_ids)[0] if np.ndim(rec.led_ids) == 1 else None
    _check_shape(name, "/tracker/led_ids", rec.led_ids, (None,))
    _check_integer(name, "/tracker/led_ids", rec.led_ids)
    _check_shape(name, "/tracker/frame_index", rec.frame_index, (n,))
    _check_shape(name, "/tracker/positions", rec.positions, (n, m, 3))
    if n:
        _check_increasing(name, "/tracker/time", rec.time)
    if rec.status is not None:
        _check_shape(name, "/tracker/status", rec.status, (n, m))
    if rec.temperature is not None:
        _check_shape(name, "/tracker/temperature", rec.temperature, (n,))
    if rec.robot is not None:
        _check_shape(name, "/robot/time", rec.robot.time, (None,))
        k = rec.robot.time.shape[0]
        _check_shape(name, "/robot/joints", rec.robot.joints, (k, None))
        if k:
            _check_increasing(name, "/robot/time", rec.robot.time)
        j = rec.robot.joints.shape[1]
        if rec.robot.dh is not None:
            _check_shape(name, "/robot/dh", rec.robot.dh, (j, 4))
        if rec.robot.flange is not None:
            _check_pose(name, "/robot/flange", rec.robot.flange, ())
        if rec.robot.link_mass is not None:
            _check_shape(name, "/robot/link_mass", rec.robot.link_mass, (j,))
            mass = np.asarray(rec.robot.link_mass, np.float64)
            if not np.all(np.isfinite(mass) & (mass >= 0)):
                raise RecordingError(f"{name}: /robot/link_mass must be finite and >= 0 [kg]")
        if rec.robot.joint_limits is not None:
            _check_shape(name, "/robot/joint_limits", rec.robot.joint_limits, (j, 2))
            limits = np.asarray(rec.robot.joint_limits, np.float64)
            if not np.all(limits[:, 0] <= limits[:, 1]):
                raise RecordingError(
                    f"{name}: /robot/joint_limits rows must be [lower, upper], lower <= upper "
                    "[rad] (±inf: no limit on that side)"
                )
    if rec.program is not None:
        p = np.shape(rec.program.targets.position)[0]
        _check_pose(name, "/program/targets", rec.program.targets, (p,))
        _check_shape(name, "/program/motion", rec.program.motion, (p,))
        _check_shape(name, "/program/speed", rec.program.speed, (p,))
        if rec.program.segment is not None:
            _check_shape(name, "/program/segment", rec.program.segment, (n,))
    if rec.tool is not None:
        mt = np.shape(rec.tool.led_ids)[0]
        _check_integer(name, "/tool/led_ids", rec.tool.led_ids)
        _check_shape(name, "/tool/constellation", rec.tool.constellation, (mt, 3))
        if rec.tool.normals is not None:
            _check_shape(name, "/tool/normals", rec.tool.normals, (mt, 3))
        if rec.tool.reference_leds is not None:
            _check_shape(name, "/tool/reference_leds", rec.tool.reference_leds, (3,))
        if rec.tool.flange_from_tool is not None:
            _check_pose(name, "/tool/flange_from_tool", rec.tool.flange_from_tool, ())
    if rec.probe is not None:
        s = np.shape(rec.probe.time)[0]
        _check_shape(name, "/probe/time", rec.probe.time, (s,))
        if s:
            _check_increasing(name, "/probe/time", rec.probe.time)
        _check_pose(name, "/probe/tool_pose", rec.probe.tool_pose, (s,))
    if rec.truth is not None:
        _check_pose(name, "/truth/tool_pose", rec.truth.tool_pose, (n,))
        _check_pose(name, "/truth/camera_from_base", rec.truth.camera_from_base, ())
        _check_pose(name, "/truth/flange_from_tool", rec.truth.flange_from_tool, ())
        _check_shape(name, "/truth/constellation", rec.truth.constellation, (None, 3))


# ----------------------------------------------------------------------------- appending


def _shuffle_deflate(chunk: np.ndarray) -> bytes:
    """A chunk as HDF5's shuffle then deflate filters store it (a zlib stream).

    Shuffle regroups the bytes by their position in the element (all first bytes, then
    all second bytes, ...); for one-byte elements it changes nothing. With ISA-L (the
    `isal` package) each such byte plane is deflated as blocks of its own (a sync flush
    ends them), so each plane gets the Huffman code of its own bytes; without it, zlib
    level 1 with run-length matching only. Any inflater reads either stream."""
    a = np.ascontiguousarray(chunk)
    planes = np.ascontiguousarray(a.view(np.uint8).reshape(a.size, a.itemsize).T)
    if _isal_zlib is not None:
        z = _isal_zlib.compressobj(1)
        parts = []
        for plane in planes:
            parts.append(z.compress(plane))
            parts.append(z.flush(_isal_zlib.Z_SYNC_FLUSH))
        parts.append(z.flush())
        return b"".join(parts)
    # run-length matching only: on shuffled positions it deflates to the size of level 1's
    # default strategy in well under half the time
    z = zlib.compressobj(1, zlib.DEFLATED, 15, 8, zlib.Z_RLE)
    return z.compress(planes) + z.flush()


# The tracker datasets in the order every flush writes them. /tracker/time goes last: a
# frame whose time is on disk has every other dataset's data on disk (see RecordingAppender).
_APPEND_ORDER = ("positions", "status", "temperature", "frame_index", "time")
# Superblock version 2 (no "open for write" flag, unlike the version 3 of SWMR files), v1
# B-tree chunk indexes, and a file-space strategy (which needs the v110 bound) that never
# reuses freed space: a rewritten chunk never lands on bytes the last commit points to.
_APPEND_LIBVER = ("earliest", "v110")


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class RecordingAppender:
    """Write a schema-1 recording frame by frame, as a recorder does, so that a crash at
    any moment leaves a file that any HDF5 reader opens.

    The tracker datasets are chunked along time and resizable. `append()` opens the file
    (if it is not open) and writes the frames; `flush()` closes it and syncs it to disk,
    which commits them. Between flushes the file is closed, so what ``kill -9`` or a power
    cut leaves there is a complete HDF5 file: plain ``h5py.File(path, "r")`` opens it.
    The file is never in SWMR mode, whose "open for write" flag a killed writer leaves set.

    While a flush is under way (milliseconds) the writes are ordered so that a kill
    leaves the previous commit readable by `read_recording`:

    - the file is created complete (empty datasets) under a temporary name and renamed;
    - no byte the last commit points to is overwritten: a chunk rewritten with another
      size goes to new space at the end of the file (file-space strategy "none": freed
      space is never reused; and the (at least three) datasets are written in a fixed
      order, so the old copy of a rewritten chunk is never the last block of the file,
      which HDF5 would give back and reuse at once);
    - the datasets are written and flushed one after the other, /tracker/time last.
      A dataset's extent can reach the disk before its chunk index; the frames it then
      claims read as the fill value, or the padding of the last chunk: NaN for
      /tracker/time. `read_recording` drops such trailing frames of a ``source="device"``
      file, and those of datasets longer than the shortest one; a frame with a time is
      then complete in every dataset;
    - the superblock's end-of-file address is written last: until it is, the new chunks
      lie beyond it and plain reads of them fail; `read_recording` then reads in SWMR
      mode, which does not check reads against that address.

    Not covered: a flush that splits a node of a chunk index (a v1 B-tree; one flush in 32
    to 64 chunks, 32 to 64 s at 1000 Hz) writes the parent node before the new one, and a
    kill in the microseconds between those two writes leaves that index broken.

    **Arguments:**

    - `path`: the new file; refused if it exists unless `overwrite`.
    - `led_ids`: `(M,)` LED identifiers (the LED axis of `/tracker/positions`).
    - `attrs`: extra root attributes (``source`` defaults to ``"device"``).
    - `with_status`, `with_temperature`: create the optional tracker datasets.
    - `compression`: of the tracker datasets: ``"gzip"`` (level 1 after the shuffle
      filter, default), ``"lzf"`` or None (a recorder may trade file size for CPU).

    With gzip the appender shuffles and deflates whole chunks itself (`_shuffle_deflate`:
    ISA-L, or zlib without the `isal` package) in a small thread pool, beside the thread
    that reads the device, and stores them with `write_direct_chunk`: the file is an
    ordinary shuffle+gzip dataset that any HDF5 reader decompresses. The last, incomplete
    chunk is stored padded and rewritten when later frames fill it. Rewritten chunks leave
    their old copies unused in the file (as SWMR writing did); ``h5repack`` compacts it.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        led_ids: np.ndarray,
        *,
        attrs: Mapping[str, Any] | None = None,
        with_status: bool = True,
        with_temperature: bool = True,
        overwrite: bool = False,
        compression: str | None = "gzip",
    ) -> None:
        self.path = Path(path)
        if compression not in ("gzip", "lzf", None):
            raise ValueError(f"compression must be 'gzip', 'lzf' or None, not {compression!r}")
        comp: dict[str, Any] = {"compression": compression}
        if compression == "gzip":
            comp.update(compression_opts=1, shuffle=True)
        elif compression == "lzf":
            comp.update(shuffle=True)
        if self.path.exists() and not overwrite:
            raise UserError(f"{self.path} exists; refusing to overwrite it (use --force)")
        self.led_ids = np.asarray(led_ids, np.int32)
        m = self.led_ids.shape[0]
        c = _TRACKER_CHUNK_FRAMES
        layout = {
            "positions": ((m, 3), np.dtype("f8")),
            "status": ((m,), np.dtype("u1")),
            "temperature": ((), np.dtype("f4")),
            "frame_index": ((), np.dtype("u8")),
            "time": ((), np.dtype("f8")),
        }
        optional = {"status": with_status, "temperature": with_temperature}
        self._keys = tuple(k for k in _APPEND_ORDER if optional.get(k, True))
        self._dtype = {k: layout[k][1] for k in self._keys}
        # the fill value of the datasets and the padding of their last chunk
        self._pad = {k: np.nan if k == "time" else 0 for k in self._keys}
        root = {
            "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "source": "device",
            **(attrs or {}),
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
        }
        tmp = self.path.with_name(f".{self.path.name}.tmp-{os.getpid()}")
        try:
            with h5py.File(tmp, "w", libver=_APPEND_LIBVER, fs_strategy="none") as f:
                for k, v in root.items():
                    f.attrs[k] = v
                t = f.create_group("tracker")
                t.create_dataset("led_ids", data=self.led_ids)
                for key in self._keys:
                    shape, dtype = layout[key]
                    ds = t.create_dataset(
                        key,
                        (0, *shape),
                        dtype,
                        maxshape=(None, *shape),
                        chunks=(c, *shape),
                        fillvalue=self._pad[key],
                        **comp,
                    )
                    # create the chunk index now (one chunk written and pruned): created by
                    # the first flush, the dataset's header could reach the disk before it
                    ds.resize(1, axis=0)
                    ds[0] = self._pad[key]
                    ds.flush()
                    ds.resize(0, axis=0)
            os.replace(tmp, self.path)
        finally:
            tmp.unlink(missing_ok=True)
        self._f: h5py.File | None = None
        self.n_frames = 0
        # gzip: every dataset compressed here; the frames of its last, incomplete chunk
        self._tail = (
            {k: np.full((c, *layout[k][0]), self._pad[k], self._dtype[k]) for k in self._keys}
            if compression == "gzip"
            else {}
        )
        self._pool = (
            ThreadPoolExecutor(min(4, os.cpu_count() or 1), "deflate") if self._tail else None
        )

    def append(
        self,
        time: np.ndarray,
        frame_index: np.ndarray,
        positions: np.ndarray,
        status: np.ndarray | None = None,
        temperature: np.ndarray | None = None,
    ) -> None:
        """Append `(k,)` times, `(k,)` frame indices, `(k, M, 3)` positions [m] (NaN unseen)."""
        k = int(np.shape(time)[0])
        if k == 0:
            return
        n0, n1 = self.n_frames, self.n_frames + k
        values = {"time": time, "frame_index": frame_index, "positions": positions}
        if "status" in self._keys:
            values["status"] = (
                status if status is not None else np.where(np.isnan(positions[..., 0]), 1, 0)
            )
        if "temperature" in self._keys:
            values["temperature"] = (
                temperature if temperature is not None else np.full(k, np.nan, np.float32)
            )
        values = {
            key: np.asarray(values[key]).astype(self._dtype[key], copy=False) for key in self._keys
        }
        chunks = self._compress(values, n0, n1) if self._tail else {}
        if self._f is None:
            self._f = self._open()
        datasets = [self._f["tracker"][key] for key in self._keys]
        for key, ds in zip(self._keys, datasets, strict=True):
            ds.resize(n1, axis=0)
            if key in chunks:  # stored now, indexed in the metadata cache
                for offset, blob in chunks[key]:
                    ds.id.write_direct_chunk(offset, blob)
            else:  # into the chunk cache
                ds[n0:n1] = values[key]
        for ds in datasets:  # chunks and index one dataset after the other, /tracker/time last
            ds.flush()
        self.n_frames = n1

    def _open(self) -> h5py.File:
        # no file locking: a reader holding the file open must not stop the recording
        return h5py.File(self.path, "r+", locking=False)

    def _compress(
        self, values: dict[str, np.ndarray], n0: int, n1: int
    ) -> dict[str, list[tuple[tuple[int, ...], bytes]]]:
        """Frames `n0:n1` as shuffled, deflated whole chunks: (chunk offset, blob) per dataset."""
        c = _TRACKER_CHUNK_FRAMES
        jobs = []  # (dataset name, chunk offset, uncompressed chunk)
        for key in self._keys:
            v, tail = values[key], self._tail[key]
            for start in range(n0 - n0 % c, n1, c):
                lo, hi = max(start, n0), min(start + c, n1)
                if hi - start < c or lo > start:  # the incomplete chunk lives in `tail`
                    if lo == start:
                        tail[:] = self._pad[key]
                    tail[lo - start : hi - start] = v[lo - n0 : hi - n0]
                    chunk = tail.copy()
                else:
                    chunk = v[lo - n0 : hi - n0]
                jobs.append((key, (start,) + (0,) * (v.ndim - 1), chunk))
        blobs = self._pool.map(_shuffle_deflate, [chunk for _, _, chunk in jobs])
        out: dict[str, list[tuple[tuple[int, ...], bytes]]] = {key: [] for key in self._keys}
        for (key, offset, _), blob in zip(jobs, blobs, strict=True):
            out[key].append((offset, blob))
        return out

    def flush(self) -> None:
        """Commit what was appended: close the file (superblock last) and sync it to disk."""
        if self._f is None:
            return
        self._f.close()
        self._f = None
        _fsync(self.path)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
        self.flush()

    def __enter__(self) -> RecordingAppender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
