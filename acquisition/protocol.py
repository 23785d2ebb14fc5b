"""robtraj's own device stream protocol: encoder and incremental decoder (see PROTOCOL.md).

Framed binary, little-endian::

    0    2  sync 0xA5 0xC4
    2    2  body length L (u16)
    4    2  CRC-16/CCITT-FALSE of bytes 0..3
    6    L  body
    6+L  2  CRC-16/CCITT-FALSE of the body

`Decoder.feed` takes byte chunks split anywhere and returns the events completed so far
(`LedFrame`, `StatusMessage`, `EndOfStream`); after any corruption it resynchronises on
the next sync that starts a frame with valid CRCs, so it never invents a frame and loses
only the frames whose bytes were damaged.
"""

from __future__ import annotations

import binascii
import functools
import struct

import numpy as np

from .events import EndOfStream, LedFrame, LedFrames, StatusMessage

SYNC = b"\xa5\xc4"
HEADER_SIZE = 6
CRC_SIZE = 2
TYPE_LED_FRAME = 0x01
TYPE_STATUS = 0x02
TYPE_END_OF_STREAM = 0x03
MAX_LEDS = 255
LED_FRAME_FIXED = 14  # u8 type, u32 counter, u64 time, u8 n
LED_RECORD = 14  # u8 id, u8 status, 3 x f32
STATUS_BODY = 13  # u8 type, u64 time, f32 temperature
MAX_BODY = LED_FRAME_FIXED + MAX_LEDS * LED_RECORD
COUNTER_MODULUS = 1 << 32

STATUS_OK = 0
STATUS_MISSING = 1
STATUS_OUT_OF_VOLUME = 2
STATUS_LOW_SIGNAL = 3

LED_DTYPE = np.dtype([("id", "u1"), ("status", "u1"), ("xyz", "<f4", (3,))])
_HEAD = struct.Struct("<2sHH")
_LEN_CRC = struct.Struct("<HH")
_LED_FIXED = struct.Struct("<BIQB")
_STATUS = struct.Struct("<BQf")
_U16 = struct.Struct("<H")


def crc16(data: bytes | bytearray | memoryview, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor.

    ``crc16(b"123456789") == 0x29B1``. `binascii.crc_hqx` is this CRC (in C).
    """
    return binascii.crc_hqx(data, crc)


def frame(body: bytes) -> bytes:
    """Wrap a message body in sync, length, header CRC and body CRC."""
    if not 1 <= len(body) <= MAX_BODY:
        raise ValueError(f"body length {len(body)} outside 1..{MAX_BODY}")
    head = SYNC + _U16.pack(len(body))
    return head + _U16.pack(crc16(head)) + body + _U16.pack(crc16(body))


def led_frame_body(
    frame_counter: int,
    time_us: int,
    led_ids: np.ndarray,
    positions_mm: np.ndarray,
    status: np.ndarray,
) -> bytes:
    """Body of an LED frame: `positions_mm` `(n, 3)` float32 [mm], NaN allowed."""
    n = int(np.shape(led_ids)[0])
    if n > MAX_LEDS:
        raise ValueError(f"{n} LEDs in one frame; the protocol carries at most {MAX_LEDS}")
    rec = np.empty(n, LED_DTYPE)
    rec["id"] = led_ids
    rec["status"] = status
    rec["xyz"] = positions_mm
    head = _LED_FIXED.pack(TYPE_LED_FRAME, frame_counter % COUNTER_MODULUS, time_us, n)
    return head + rec.tobytes()


def encode_led_frame(
    frame_counter: int,
    time_us: int,
    led_ids: np.ndarray,
    positions_mm: np.ndarray,
    status: np.ndarray,
) -> bytes:
    """One framed LED frame (counter taken modulo 2**32, positions in mm as float32)."""
    return frame(led_frame_body(frame_counter, time_us, led_ids, positions_mm, status))


def encode_status(time_us: int, temperature: float) -> bytes:
    return frame(_STATUS.pack(TYPE_STATUS, time_us, temperature))


def encode_end_of_stream() -> bytes:
    return frame(bytes([TYPE_END_OF_STREAM]))


def seconds_to_us(t: float) -> int:
    return int(round(float(t) * 1e6))


def encode_event(event: LedFrame | StatusMessage | EndOfStream) -> bytes:
    """Encode a decoder event (positions [m] -> float32 mm, time [s] -> integer µs)."""
    if isinstance(event, LedFrame):
        pos_mm = np.asarray(np.asarray(event.positions, np.float64) * 1000.0, np.float32)
        return encode_led_frame(
            event.frame_counter,
            seconds_to_us(event.device_time),
            np.asarray(event.led_ids),
            pos_mm,
            np.asarray(event.status),
        )
    if isinstance(event, StatusMessage):
        return encode_status(seconds_to_us(event.device_time), event.temperature)
    if isinstance(event, EndOfStream):
        return encode_end_of_stream()
    raise TypeError(f"cannot encode {type(event).__name__}")


ERROR_COUNTERS = ("bad_header_crc", "bad_body_crc", "bad_length", "unknown_type", "truncated")

# ----------------------------------------------------------------------------- batch checks

# the CRC-16/CCITT-FALSE register after one byte b from register 0 (the byte-wise table)
_CRC_BYTE = np.array([binascii.crc_hqx(bytes([b]), 0) for b in range(256)], np.uint16)
_VECTOR_CRC_MIN = 4  # runs shorter than this are checked message by message
_MAX_RUN = 4096  # frames checked in one vectorised pass (bounds the temporaries)


@functools.lru_cache(maxsize=4)
def _crc_tables(length: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Tables that give the CRC-16/CCITT-FALSE of many `length`-byte messages at once.

    The CRC is affine in the message bits: ``crc16(m) = base ^ XOR_j T[j, m[j]]`` with
    ``base = crc16(zeros(length))`` and ``T[j, b]`` the CRC from register 0 of the byte b
    followed by ``length - 1 - j`` zero bytes. Returns T flattened, the row offsets
    ``256 j`` and base."""
    table = np.empty((length, 256), np.uint16)
    row = _CRC_BYTE
    table[length - 1] = row
    for j in range(length - 2, -1, -1):  # one more zero byte after b: shift the register
        row = (row << 8) ^ _CRC_BYTE[row >> 8]
        table[j] = row
    offsets = np.arange(length, dtype=np.intp) * 256
    return table.ravel(), offsets, binascii.crc_hqx(bytes(length), 0xFFFF)


def crc16_rows(messages: np.ndarray) -> np.ndarray:
    """`crc16` of each row of a `(K, L)` uint8 array (any strides), as `(K,)` uint16."""
    table, offsets, base = _crc_tables(messages.shape[1])
    return np.bitwise_xor.reduce(table[messages + offsets], axis=1) ^ np.uint16(base)


@functools.cache
def _frame_dtype(n: int) -> np.dtype:
    """A whole framed LED frame with `n` LED records, as one structured element."""
    return np.dtype(
        [
            ("head", "V6"),
            ("type", "u1"),
            ("counter", "<u4"),
            ("time", "<u8"),
            ("n", "u1"),
            ("leds", LED_DTYPE, (n,)),
            ("crc", "<u2"),
        ]
    )


def _led_run(raw: np.ndarray, i: int, length: int, end: int) -> int:
    """How many LED frames, the first at `i`, follow one another in `raw[:end]` and pass
    every check: the first one's header was checked (CRC, length, and the LED count n
    fits the length); each following one repeats that header's bytes (sync, length,
    header CRC), its type byte and its n; each body matches its CRC. 0: the first body
    does not."""
    stride = length + HEADER_SIZE + CRC_SIZE
    count = min((end - i) // stride, _MAX_RUN)
    rows = raw[i : i + count * stride].reshape(count, stride)
    if count > 1:
        fixed = HEADER_SIZE + 1  # sync, length, header CRC, type
        n_at = HEADER_SIZE + LED_FRAME_FIXED - 1
        same = np.all(rows[1:, :fixed] == rows[0, :fixed], axis=1)
        same &= rows[1:, n_at] == rows[0, n_at]
        if not same.all():
            count = 1 + int(np.argmin(same))
            rows = rows[:count]
    bodies = rows[:, HEADER_SIZE : HEADER_SIZE + length]
    if count >= _VECTOR_CRC_MIN:
        got = crc16_rows(bodies)
    else:
        got = np.array([binascii.crc_hqx(b.tobytes(), 0xFFFF) for b in bodies], np.uint16)
    sent = rows[:, -2] | (rows[:, -1].astype(np.uint16) << 8)
    ok = got == sent
    return count if ok.all() else int(np.argmin(ok))


_RUN = object()  # placeholder in the event list for a run of LED frames


class Decoder:
    """Incremental decoder for the robtraj stream; follows `acquisition.events`.

    `feed(chunk)` returns the events completed by `chunk`; `finish()` declares the
    stream (or this connection) over: an incomplete frame left in the buffer counts as
    ``truncated`` and the bytes after its sync are still searched for frames.

    `blocks`: yield consecutive LED frames (same LED count, no other message between
    them) as one `LedFrames` instead of one `LedFrame` each: the same frames, without a
    Python object per frame (what the recorder uses).

    LED frames that follow one another with the same header are checked together: their
    header bytes against the first one's, which was checked, and all their body CRCs in
    one vectorised pass (`crc16_rows`). The checks are the same as message by message.

    `counters`:

    - ``led_frames``, ``status_messages``, ``end_of_stream``: messages decoded.
    - ``bad_header_crc``: a sync whose header CRC does not match (a corrupted header or a
      sync pattern inside other bytes).
    - ``bad_length``: a header with a valid CRC but a length outside ``1..3584``, or a
      body whose length does not fit its type.
    - ``bad_body_crc``: a valid header whose body CRC does not match (a corrupted or
      truncated message).
    - ``unknown_type``: a body with valid CRC and an unknown type byte.
    - ``truncated``: an incomplete message at `finish()` (connection lost mid-message).
    - ``resyncs``: stretches of undecodable bytes between two messages, i.e. how often
      the decoder had to search for the next sync; ``bytes_skipped``: their total length.
    """

    def __init__(self, blocks: bool = False) -> None:
        self.blocks = blocks
        self._buf = bytearray()
        self._junk = False  # inside an undecodable stretch since the last good message
        self.counters: dict[str, int] = {
            "led_frames": 0,
            "status_messages": 0,
            "end_of_stream": 0,
            "bad_header_crc": 0,
            "bad_body_crc": 0,
            "bad_length": 0,
            "unknown_type": 0,
            "truncated": 0,
            "resyncs": 0,
            "bytes_skipped": 0,
        }

    def feed(self, chunk: bytes | bytearray | memoryview) -> list:
        self._buf += chunk
        return self._scan(final=False)

    def finish(self) -> list:
        events = self._scan(final=True)
        if self._buf:
            self._skip(len(self._buf))
            del self._buf[:]
        self._end_junk()
        return events

    # --------------------------------------------------------------------- internals

    def _skip(self, n: int) -> None:
        if n > 0:
            self.counters["bytes_skipped"] += n
            self._junk = True

    def _end_junk(self) -> None:
        if self._junk:
            self.counters["resyncs"] += 1
            self._junk = False

    def _scan(self, final: bool) -> list:
        buf = self._buf
        n = len(buf)
        c = self.counters
        crc = binascii.crc_hqx  # CRC-16/CCITT-FALSE with init 0xFFFF, see crc16()
        mv = memoryview(buf)
        raw = np.frombuffer(buf, np.uint8)  # both released before the buffer is resized
        out: list = []
        runs: list[tuple[int, int, int, int]] = []  # (slot in out, offset, frames, LEDs)
        pos = 0
        try:
            while True:
                i = buf.find(SYNC, pos)
                if i < 0:
                    keep = n if final or n == pos or buf[n - 1] != 0xA5 else n - 1
                    self._skip(keep - pos)
                    pos = keep
                    break
                self._skip(i - pos)
                pos = i
                if n - i < HEADER_SIZE:
                    if final:
                        c["truncated"] += 1
                        self._skip(1)
                        pos = i + 1
                        continue
                    break
                length, hcrc = _LEN_CRC.unpack_from(buf, i + 2)
                if crc(mv[i : i + 4], 0xFFFF) != hcrc:
                    c["bad_header_crc"] += 1
                    self._skip(1)
                    pos = i + 1
                    continue
                if not 1 <= length <= MAX_BODY:
                    c["bad_length"] += 1
                    self._skip(1)
                    pos = i + 1
                    continue
                start = i + HEADER_SIZE
                end = start + length + CRC_SIZE
                if end > n:
                    if final:
                        c["truncated"] += 1
                        self._skip(1)
                        pos = i + 1
                        continue
                    break
                kind = buf[start]
                if (
                    kind == TYPE_LED_FRAME
                    and length >= LED_FRAME_FIXED
                    and length == LED_FRAME_FIXED + LED_RECORD * buf[start + LED_FRAME_FIXED - 1]
                ):
                    count = _led_run(raw, i, length, n)
                    if not count:
                        c["bad_body_crc"] += 1
                        self._skip(1)
                        pos = i + 1
                        continue
                    self._end_junk()
                    runs.append((len(out), i, count, buf[start + LED_FRAME_FIXED - 1]))
                    out.append(_RUN)
                    pos = i + count * (end - i)
                    continue
                if crc(mv[start : end - CRC_SIZE], 0xFFFF) != _U16.unpack_from(buf, end - 2)[0]:
                    c["bad_body_crc"] += 1
                    self._skip(1)
                    pos = i + 1
                    continue
                if kind == TYPE_LED_FRAME:  # too short for the fixed fields, or n not fitting
                    c["bad_length"] += 1
                    event = None
                else:
                    event = self._parse(bytes(buf[start : end - CRC_SIZE]))
                if event is None:
                    self._skip(1)
                    pos = i + 1
                    continue
                self._end_junk()
                out.append(event)
                pos = end
            if runs:
                out = self._fill_led_frames(out, runs, raw)
        finally:
            mv.release()
            del raw  # the buffer can be resized again
        if pos:
            del buf[:pos]
        return out

    def _fill_led_frames(self, out: list, runs: list, raw: np.ndarray) -> list:
        """Replace the runs' placeholders by `LedFrames` blocks (adjacent runs of the same
        LED count merged) or, without `blocks`, by their `LedFrame`s."""
        self.counters["led_frames"] += sum(r[2] for r in runs)
        groups: list[list[tuple[int, int, int, int]]] = []
        for run in runs:
            last = groups[-1][-1] if groups else None
            if self.blocks and last is not None and last[0] + 1 == run[0] and last[3] == run[3]:
                groups[-1].append(run)
            else:
                groups.append([run])
        events: dict[int, list] = {}
        for group in groups:
            block = _led_frames(raw, group)
            events[group[0][0]] = [block] if self.blocks else list(block.frames())
        result: list = []
        for slot, ev in enumerate(out):
            if ev is _RUN:
                result += events.get(slot, ())
            else:
                result.append(ev)
        return result

    def _parse(self, body: bytes) -> StatusMessage | EndOfStream | None:
        c = self.counters
        kind = body[0]
        if kind == TYPE_STATUS:
            if len(body) != STATUS_BODY:
                c["bad_length"] += 1
                return None
            _, time_us, temperature = _STATUS.unpack(body)
            c["status_messages"] += 1
            return StatusMessage(device_time=time_us / 1e6, temperature=temperature)
        if kind == TYPE_END_OF_STREAM:
            if len(body) != 1:
                c["bad_length"] += 1
                return None
            c["end_of_stream"] += 1
            return EndOfStream()
        c["unknown_type"] += 1
        return None


def _led_frames(raw: np.ndarray, runs: list[tuple[int, int, int, int]]) -> LedFrames:
    """The checked LED frames of `runs` (offset, frames, n LEDs each) as arrays (copies)."""
    dtype = _frame_dtype(runs[0][3])
    parts = [raw[off : off + count * dtype.itemsize].view(dtype) for _, off, count, _ in runs]
    recs = parts[0] if len(parts) == 1 else np.concatenate(parts)
    leds = recs["leds"]
    status = leds["status"].copy()
    positions = leds["xyz"].astype(np.float64)
    positions /= 1000.0
    positions[status == STATUS_MISSING] = np.nan
    return LedFrames(
        frame_counter=recs["counter"].astype(np.int64),
        device_time=recs["time"] / 1e6,
        led_ids=leds["id"].astype(np.int64),
        positions=positions,
        status=status,
    )
