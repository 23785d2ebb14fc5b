"""OptiTrack NatNet 3.0 packets: a frame-of-data decoder and a stream decoder.

A NatNet packet is ``u16 message_id``, ``u16 payload_bytes``, then the payload, all
little-endian. `parse_packet` splits one packet; `decode_frame_of_data` decodes the
payload of a frame of data (``NAT_FRAMEOFDATA = 7``) into a `NatNetFrame` exactly as
the wire carries it (metres; quaternions converted from the wire's x, y, z, w to
robtraj's w, x, y, z). `NatNetStreamDecoder` follows the decoder interface of
`acquisition.events`: it takes a byte stream of concatenated packets (a capture
file, or UDP datagrams appended one after another), splits it on the size in each
header and yields one `LedFrame` per frame of data, with the labelled markers as
LEDs.
"""

from __future__ import annotations

import dataclasses
import os
import struct
from pathlib import Path

import numpy as np

from robtraj import Recording, UserError

from .events import EndOfStream, LedFrame, StatusMessage

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_DISCONNECTBYTIMEOUT = 11
NAT_ECHOREQUEST = 12
NAT_ECHORESPONSE = 13
NAT_DISCOVERY = 14
NAT_UNRECOGNIZED_REQUEST = 100

_KNOWN_MESSAGES = frozenset(range(15)) | {NAT_UNRECOGNIZED_REQUEST}

# labelled-marker params bits
MARKER_OCCLUDED = 0x01
MARKER_PC_SOLVED = 0x02
MARKER_MODEL_SOLVED = 0x04
MARKER_HAS_MODEL = 0x08
MARKER_UNLABELED = 0x10
MARKER_ACTIVE = 0x20
# rigid-body params bits
RIGID_BODY_TRACKING_VALID = 0x01


class NatNetError(ValueError):
    """A NatNet packet that cannot be decoded (truncated, wrong size, trailing bytes)."""


@dataclasses.dataclass(frozen=True)
class MarkerSet:
    name: str
    positions: np.ndarray  # (n, 3) [m]


@dataclasses.dataclass(frozen=True)
class RigidBody:
    """One rigid body: `position` [m], `quaternion_wxyz` (wire order is x, y, z, w)."""

    id: int
    position: np.ndarray
    quaternion_wxyz: np.ndarray
    mean_error: float
    params: int

    @property
    def tracking_valid(self) -> bool:
        return bool(self.params & RIGID_BODY_TRACKING_VALID)


@dataclasses.dataclass(frozen=True)
class Skeleton:
    id: int
    rigid_bodies: list[RigidBody]


@dataclasses.dataclass(frozen=True)
class LabeledMarker:
    """A labelled marker; the wire id is ``(model_id << 16) | marker_id``."""

    marker_id: int
    model_id: int
    position: np.ndarray
    size: float
    params: int
    residual: float

    @property
    def occluded(self) -> bool:
        return bool(self.params & MARKER_OCCLUDED)

    @property
    def point_cloud_solved(self) -> bool:
        return bool(self.params & MARKER_PC_SOLVED)

    @property
    def model_solved(self) -> bool:
        return bool(self.params & MARKER_MODEL_SOLVED)

    @property
    def unlabeled(self) -> bool:
        return bool(self.params & MARKER_UNLABELED)

    @property
    def wire_id(self) -> int:
        return (self.model_id << 16) | self.marker_id


@dataclasses.dataclass(frozen=True)
class AnalogDevice:
    """A force plate or other analog device: `channels` is one array of samples per channel."""

    id: int
    channels: list[np.ndarray]


@dataclasses.dataclass(frozen=True)
class NatNetFrame:
    """One NatNet 3.0 frame of data, as sent (positions in metres)."""

    frame_number: int
    marker_sets: list[MarkerSet]
    unlabeled_markers: np.ndarray  # (n, 3) [m]
    rigid_bodies: list[RigidBody]
    skeletons: list[Skeleton]
    labeled_markers: list[LabeledMarker]
    force_plates: list[AnalogDevice]
    devices: list[AnalogDevice]
    timecode: int
    timecode_sub: int
    timestamp: float  # [s]
    stamp_camera_mid_exposure: int  # high-resolution clock ticks
    stamp_data_received: int
    stamp_transmit: int
    params: int

    @property
    def is_recording(self) -> bool:
        return bool(self.params & 0x01)

    @property
    def tracked_models_changed(self) -> bool:
        return bool(self.params & 0x02)


class _Reader:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def take(self, fmt: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise NatNetError(
                f"frame of data truncated: needs {self.pos + size} bytes, has {len(self.data)}"
            )
        out = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return out

    def one(self, fmt: str):
        return self.take(fmt)[0]

    def count(self, what: str, item_bytes: int) -> int:
        n = self.one("<i")
        if n < 0 or n * item_bytes > len(self.data) - self.pos:
            raise NatNetError(f"frame of data: implausible {what} count {n}")
        return n

    def floats(self, n: int) -> np.ndarray:
        return np.asarray(self.take(f"<{n}f"), np.float64)

    def cstring(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise NatNetError("frame of data: unterminated marker-set name")
        s = self.data[self.pos : end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return s


def _rigid_body(r: _Reader) -> RigidBody:
    rb_id = r.one("<i")
    pos = r.floats(3)
    qx, qy, qz, qw = r.floats(4)
    mean_error = float(r.one("<f"))
    params = r.one("<h")
    return RigidBody(rb_id, pos, np.array([qw, qx, qy, qz]), mean_error, params)


def _analog(r: _Reader) -> AnalogDevice:
    dev_id = r.one("<i")
    n_channels = r.count("channel", 4)
    channels = []
    for _ in range(n_channels):
        n = r.count("sample", 4)
        channels.append(r.floats(n))
    return AnalogDevice(dev_id, channels)


def decode_frame_of_data(payload: bytes) -> NatNetFrame:
    """Decode a NatNet 3.0 frame-of-data payload (the bytes after the 4-byte header)."""
    r = _Reader(payload)
    frame_number = r.one("<i")
    marker_sets = []
    for _ in range(r.count("marker set", 5)):
        name = r.cstring()
        n = r.count("marker", 12)
        marker_sets.append(MarkerSet(name, r.floats(3 * n).reshape(n, 3)))
    n = r.count("unlabelled marker", 12)
    unlabeled = r.floats(3 * n).reshape(n, 3)
    rigid_bodies = [_rigid_body(r) for _ in range(r.count("rigid body", 38))]
    skeletons = []
    for _ in range(r.count("skeleton", 8)):
        sk_id = r.one("<i")
        skeletons.append(Skeleton(sk_id, [_rigid_body(r) for _ in range(r.count("body", 38))]))
    labeled = []
    for _ in range(r.count("labelled marker", 26)):
        marker_id, model_id = r.take("<HH")
        pos = r.floats(3)
        size = float(r.one("<f"))
        params = r.one("<h")
        residual = float(r.one("<f"))
        labeled.append(LabeledMarker(marker_id, model_id, pos, size, params, residual))
    force_plates = [_analog(r) for _ in range(r.count("force plate", 8))]
    devices = [_analog(r) for _ in range(r.count("device", 8))]
    timecode, timecode_sub = r.take("<II")
    timestamp = float(r.one("<d"))
    mid, received, transmit = r.take("<QQQ")
    params = r.one("<h")
    r.take("<i")  # end of data tag
    if r.pos != len(payload):
        raise NatNetError(f"frame of data: {len(payload) - r.pos} unexpected trailing bytes")
    return NatNetFrame(
        frame_number=frame_number,
        marker_sets=marker_sets,
        unlabeled_markers=unlabeled,
        rigid_bodies=rigid_bodies,
        skeletons=skeletons,
        labeled_markers=labeled,
        force_plates=force_plates,
        devices=devices,
        timecode=timecode,
        timecode_sub=timecode_sub,
        timestamp=timestamp,
        stamp_camera_mid_exposure=mid,
        stamp_data_received=received,
        stamp_transmit=transmit,
        params=params,
    )


def parse_packet(packet: bytes) -> tuple[int, bytes]:
    """Split one whole packet into ``(message_id, payload)``; the size must match."""
    if len(packet) < 4:
        raise NatNetError(f"packet of {len(packet)} bytes is shorter than its 4-byte header")
    message_id, size = struct.unpack_from("<HH", packet)
    if len(packet) != 4 + size:
        raise NatNetError(f"packet header says {4 + size} bytes, packet has {len(packet)}")
    return message_id, bytes(packet[4:])


def decode_packet(packet: bytes) -> NatNetFrame:
    """Decode one whole frame-of-data packet (header included)."""
    message_id, payload = parse_packet(packet)
    if message_id != NAT_FRAMEOFDATA:
        raise NatNetError(f"message id {message_id} is not a frame of data ({NAT_FRAMEOFDATA})")
    return decode_frame_of_data(payload)


class NatNetStreamDecoder:
    """Decode a byte stream of concatenated NatNet packets into `LedFrame` events.

    Labelled markers become LEDs: with `model_id` given, only that model's markers,
    ``led_id`` = the marker id; without it, every labelled marker with ``led_id`` = the
    32-bit NatNet id ``(model_id << 16) | marker_id`` (= the marker id for markers of
    no model). With `led_ids` given every frame reports exactly those LEDs, in that
    order, and one the frame does not carry is missing (status 1, NaN); a marker sent
    with its occluded bit set is missing too. Positions are metres (NatNet's unit),
    ``frame_counter`` is the NatNet frame number and ``device_time`` its timestamp [s].

    `counters` counts ``packets``, ``frames``, ``other_messages`` (non-frame
    messages, skipped), ``malformed`` (frames that failed to decode, skipped) and
    ``resync_bytes`` (bytes dropped because no plausible header started there).
    """

    def __init__(
        self,
        model_id: int | None = None,
        led_ids: list[int] | np.ndarray | None = None,
        include_unlabeled: bool = False,
    ) -> None:
        self.model_id = model_id
        self.led_ids = None if led_ids is None else np.asarray(led_ids, np.int64)
        self.include_unlabeled = include_unlabeled
        self._buffer = bytearray()
        self.counters: dict[str, int] = {
            "packets": 0,
            "frames": 0,
            "other_messages": 0,
            "malformed": 0,
            "resync_bytes": 0,
        }

    def feed(self, chunk: bytes) -> list[LedFrame | StatusMessage | EndOfStream]:
        self._buffer.extend(chunk)
        events: list[LedFrame | StatusMessage | EndOfStream] = []
        buf = self._buffer
        while len(buf) >= 4:
            message_id, size = struct.unpack_from("<HH", buf)
            if message_id not in _KNOWN_MESSAGES:
                del buf[:1]
                self.counters["resync_bytes"] += 1
                continue
            if len(buf) < 4 + size:
                break
            payload = bytes(buf[4 : 4 + size])
            del buf[: 4 + size]
            self.counters["packets"] += 1
            if message_id != NAT_FRAMEOFDATA:
                self.counters["other_messages"] += 1
                continue
            try:
                frame = decode_frame_of_data(payload)
            except NatNetError:
                self.counters["malformed"] += 1
                continue
            self.counters["frames"] += 1
            events.append(self.to_led_frame(frame))
        return events

    def to_led_frame(self, frame: NatNetFrame) -> LedFrame:
        """The `LedFrame` this decoder makes of one decoded frame."""
        seen: dict[int, LabeledMarker] = {}
        for m in frame.labeled_markers:
            if m.unlabeled and not self.include_unlabeled:
                continue
            if self.model_id is not None:
                if m.model_id != self.model_id:
                    continue
                seen[m.marker_id] = m
            else:
                seen[m.wire_id] = m
        ids = np.asarray(sorted(seen), np.int64) if self.led_ids is None else self.led_ids
        n = ids.shape[0]
        positions = np.full((n, 3), np.nan)
        status = np.ones(n, np.uint8)
        for i, led in enumerate(ids.tolist()):
            m = seen.get(led)
            if m is not None and not m.occluded:
                positions[i] = m.position
                status[i] = 0
        return LedFrame(
            frame_counter=frame.frame_number,
            device_time=frame.timestamp,
            led_ids=ids,
            positions=positions,
            status=status,
        )


def import_natnet(
    path: str | os.PathLike, *, model_id: int | None = None, rate: float | None = None
) -> Recording:
    """A capture file of concatenated NatNet packets as a schema-1 `Recording`.

    LEDs are the labelled markers (see `NatNetStreamDecoder`), the union over all
    frames; ``time`` is the NatNet timestamp [s] (or ``frame / rate`` with `rate` [Hz]),
    ``frame_index`` the frame number counted from the first frame.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise UserError(f"{path}: cannot read ({e.strerror or e})") from None
    decoder = NatNetStreamDecoder(model_id=model_id)
    frames = [e for e in decoder.feed(data) if isinstance(e, LedFrame)]
    if not frames:
        raise UserError(
            f"{path}: no NatNet frame of data decoded ({decoder.counters['packets']} packets, "
            f"{decoder.counters['malformed']} malformed, {decoder.counters['resync_bytes']} "
            "bytes skipped)"
        )
    frames.sort(key=lambda f: f.frame_counter)
    led_ids = np.asarray(sorted({int(i) for f in frames for i in f.led_ids}), np.int64)
    column = {led: j for j, led in enumerate(led_ids.tolist())}
    n, m = len(frames), led_ids.shape[0]
    positions = np.full((n, m, 3), np.nan)
    status = np.ones((n, m), np.uint8)
    for i, f in enumerate(frames):
        cols = [column[int(led)] for led in f.led_ids]
        positions[i, cols] = f.positions
        status[i, cols] = f.status
    counter = np.asarray([f.frame_counter for f in frames], np.int64)
    if np.any(np.diff(counter) <= 0):
        raise UserError(f"{path}: repeated NatNet frame numbers")
    if rate is None:
        time = np.asarray([f.device_time for f in frames], np.float64)
        if np.any(np.diff(time) <= 0):
            raise UserError(f"{path}: NatNet timestamps are not increasing; give --rate HZ")
    else:
        time = (counter - counter[0]) / float(rate)
    if np.any(led_ids > np.iinfo(np.int32).max):
        raise UserError(f"{path}: NatNet marker ids do not fit the schema's int32 led_ids")
    return Recording(
        time=time,
        frame_index=(counter - counter[0]).astype(np.uint64),
        led_ids=led_ids.astype(np.int32),
        positions=positions,
        status=status,
        attrs={
            "source": "import",
            "import_format": "natnet",
            "import_file": path.name,
            "natnet_first_frame": int(counter[0]),
        },
    )
