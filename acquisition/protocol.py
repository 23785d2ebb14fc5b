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
import struct

import numpy as np

from .events import EndOfStream, LedFrame, StatusMessage

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


class Decoder:
    """Incremental decoder for the robtraj stream; follows `acquisition.events`.

    `feed(chunk)` returns the events completed by `chunk`; `finish()` declares the
    stream (or this connection) over: an incomplete frame left in the buffer counts as
    ``truncated`` and the bytes after its sync are still searched for frames.

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

    def __init__(self) -> None:
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

    def feed(
        self, chunk: bytes | bytearray | memoryview
    ) -> list[LedFrame | StatusMessage | EndOfStream]:
        self._buf += chunk
        return self._scan(final=False)

    def finish(self) -> list[LedFrame | StatusMessage | EndOfStream]:
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

    def _scan(self, final: bool) -> list[LedFrame | StatusMessage | EndOfStream]:
        buf = self._buf
        n = len(buf)
        c = self.counters
        crc = binascii.crc_hqx  # CRC-16/CCITT-FALSE with init 0xFFFF, see crc16()
        mv = memoryview(buf)
        out: list = []
        leds: list[tuple[int, int, int, int, int]] = []  # (slot, counter, time_us, n, offset)
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
                if crc(mv[start : end - CRC_SIZE], 0xFFFF) != _U16.unpack_from(buf, end - 2)[0]:
                    c["bad_body_crc"] += 1
                    self._skip(1)
                    pos = i + 1
                    continue
                kind = buf[start]
                event = None
                if kind == TYPE_LED_FRAME and length >= LED_FRAME_FIXED:
                    _, counter, time_us, k = _LED_FIXED.unpack_from(buf, start)
                    if length == LED_FRAME_FIXED + k * LED_RECORD:
                        leds.append((len(out), counter, time_us, k, start + LED_FRAME_FIXED))
                        event = True  # filled in below, in one vectorised pass
                    else:
                        c["bad_length"] += 1
                else:
                    event = self._parse(bytes(buf[start : end - CRC_SIZE]))
                if event is None:
                    self._skip(1)
                    pos = i + 1
                    continue
                self._end_junk()
                out.append(event)
                pos = end
        finally:
            mv.release()  # the buffer can be resized again
        if leds:
            self._fill_led_frames(out, leds)
        if pos:
            del buf[:pos]
        return out

    def _fill_led_frames(self, out: list, leds: list[tuple[int, int, int, int, int]]) -> None:
        """Turn the LED frames found in the buffer into `LedFrame`s, one numpy pass per size."""
        self.counters["led_frames"] += len(leds)
        raw = np.frombuffer(self._buf, np.uint8)
        try:
            sizes = {k for _, _, _, k, _ in leds}
            for size in sizes:
                group = leds if len(sizes) == 1 else [m for m in leds if m[3] == size]
                if size:
                    offsets = np.fromiter((m[4] for m in group), np.int64, len(group))
                    take = offsets[:, None] + np.arange(size * LED_RECORD)
                    recs = raw[take].view(LED_DTYPE)
                else:
                    recs = np.zeros((len(group), 0), LED_DTYPE)
                status = np.ascontiguousarray(recs["status"])
                positions = recs["xyz"].astype(np.float64) / 1000.0
                positions[status == STATUS_MISSING] = np.nan
                ids = recs["id"].astype(np.int64)
                for j, (slot, counter, time_us, _, _) in enumerate(group):
                    out[slot] = LedFrame(counter, time_us / 1e6, ids[j], positions[j], status[j])
        finally:
            del raw

    def _parse(self, body: bytes) -> StatusMessage | EndOfStream | None:
        c = self.counters
        kind = body[0]
        if kind == TYPE_LED_FRAME:
            c["bad_length"] += 1  # too short to hold the fixed LED-frame fields
            return None
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
