"""Fault-tolerant recorder: read a device stream from any pyserial URL, write schema-1 HDF5.

`Recorder` opens the port, feeds every byte to a protocol decoder (`acquisition.protocols`)
and hands the decoded frames to a `FrameWriter`, which appends them to the file through
`robtraj.recording.RecordingAppender` every `write_interval` seconds and flushes (the
appender closes the file at every flush), so a crash or ``kill -9`` leaves a file that
any HDF5 reader opens and that lacks at most the last second.

Decisions (see also PROTOCOL.md):

- **LED set.** `/tracker/positions` has fixed M columns. The writer holds back the frames
  of the first `led_set_seconds` of device time (0.5 s), takes the LEDs reported in them
  (in order of first appearance) as the columns and only then creates the file. An LED id
  that first appears later is not recorded; its values are counted as
  ``unknown_led_values`` and its id is listed in the summary. (Our device reports every
  LED of the tool in every frame, status 1 when not seen, so the first frame already
  holds the whole set.)
- **Not seen** is NaN in `/tracker/positions`: status 1 (missing), non-finite coordinates
  or an LED absent from a frame (recorded with status 1).
- **Frame counter.** The u32 counter is unwrapped (`/tracker/frame_index` starts at the
  first counter received); a forward jump of d counts d - 1 lost frames; a repeated or
  backward counter (jump of 0 or >= 2**31) is dropped and counted ``out_of_order``.
- **Time.** `/tracker/time` is the device time [s]; a frame whose time does not increase
  is dropped and counted ``non_monotonic_time``.
- **Temperature** is the last status message's value (NaN before the first).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import os
import queue
import re
import select
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from robtraj import UserError
from robtraj.recording import RecordingAppender

from .events import EndOfStream, LedFrame, LedFrames, StatusMessage
from .protocols import make_decoder

_WRAP = 1 << 32
_HALF = 1 << 31


ABANDONED: list[Any] = []  # appenders left open after a failed write (see FrameWriter.abandon)


class DiskFull(Exception):
    """Writing the recording failed for lack of space; what was flushed before is kept."""


class ConnectionLost(Exception):
    """The port went away (socket closed, pty hung up, USB device unplugged)."""


def _is_disk_full(e: BaseException) -> bool:
    if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        return True
    text = str(e)
    return any(
        s in text
        for s in ("No space left", "Disk quota", "File too large", "errno = 28", "errno = 27")
    )


def _ignore_unraisable(unraisable: Any) -> None:
    pass


@contextlib.contextmanager
def _quiet_stderr_fd():
    """Point file descriptor 2 at /dev/null for the duration (C-level prints only)."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


@dataclasses.dataclass(frozen=True, eq=False)
class _Accepted:
    """A decoder block taken whole: its frame indices and the temperature of its frames."""

    index: np.ndarray
    frames: LedFrames
    temperature: float


class FrameWriter:
    """Turns decoded events into rows of a schema-1 recording at `path`.

    `frame` takes one `LedFrame`, `frames` a `LedFrames` block: a block whose counters
    all step forward and whose times all increase is taken as a whole (counted, unwrapped
    and later packed with array operations); any other block, and every block before the
    LED set is fixed, goes through `frame` one frame at a time, so both give the same
    rows and counters."""

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        overwrite: bool = False,
        attrs: dict[str, Any] | None = None,
        led_set_seconds: float = 0.5,
        appender_factory: Callable[..., Any] = RecordingAppender,
        compression: str | None = "gzip",
        threaded: bool = True,
    ) -> None:
        self.path = Path(path)
        self.compression = compression
        self.threaded = threaded
        # batches handed to the writer thread; at most 8 waiting bounds the memory held
        self._queue: queue.Queue[list | None] = queue.Queue(maxsize=8)
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self.overwrite = overwrite
        self.attrs = attrs or {}
        self.led_set_seconds = led_set_seconds
        self.appender_factory = appender_factory
        self.appender: Any = None
        self.led_ids: np.ndarray | None = None
        self._col_of: dict[int, int] = {}
        # (index, time, frame, temperature) per frame, or a block taken whole
        self._pending: list[tuple[int, float, LedFrame, float] | _Accepted] = []
        self._n_pending = 0
        self._temperature = float("nan")
        self._last_raw: int | None = None
        self._index = 0
        self._first_time: float | None = None
        self._last_time = -np.inf
        self.unknown_led_ids: set[int] = set()
        self._last_positions: np.ndarray | None = None  # of the latest frame
        self.counters = {
            "frames": 0,
            "written": 0,
            "lost": 0,
            "out_of_order": 0,
            "non_monotonic_time": 0,
            "unknown_led_values": 0,
        }

    @property
    def leds_seen(self) -> int:
        """LEDs seen (finite position) in the latest frame."""
        p = self._last_positions
        return 0 if p is None else int(np.count_nonzero(np.isfinite(p[:, 0])))

    @property
    def pending(self) -> int:
        """Frames received but not yet appended to the file."""
        return self._n_pending

    @property
    def n_leds(self) -> int | None:
        return None if self.led_ids is None else int(self.led_ids.shape[0])

    def status(self, msg: StatusMessage) -> None:
        self._temperature = float(msg.temperature)

    def frame(self, fr: LedFrame) -> None:
        c = self.counters
        raw = int(fr.frame_counter) % _WRAP
        if self._last_raw is None:
            index = raw
        else:
            d = (raw - self._last_raw) % _WRAP
            if d == 0 or d >= _HALF:
                c["out_of_order"] += 1
                return
            index = self._index + d
        t = float(fr.device_time)
        if not t > self._last_time:
            c["non_monotonic_time"] += 1
            return
        if self._last_raw is not None:
            c["lost"] += index - self._index - 1
        self._last_raw, self._index, self._last_time = raw, index, t
        if self._first_time is None:
            self._first_time = t
        self._pending.append((index, t, fr, self._temperature))
        self._n_pending += 1
        c["frames"] += 1
        self._last_positions = fr.positions
        if self.appender is None and t - self._first_time >= self.led_set_seconds:
            self._open()

    def frames(self, block: LedFrames) -> None:
        """Take a block of consecutive frames: as a whole when its counters all step
        forward (by 1 .. 2**31 - 1) and its times all increase, else frame by frame."""
        k = len(block)
        if k == 0:
            return
        if self.appender is not None and self._last_raw is not None:
            raw = block.frame_counter % _WRAP
            t = block.device_time
            step = np.empty(k, np.int64)
            step[0] = (int(raw[0]) - self._last_raw) % _WRAP
            np.subtract(raw[1:], raw[:-1], out=step[1:])
            step[1:] %= _WRAP
            if (
                ((step > 0) & (step < _HALF)).all()
                and float(t[0]) > self._last_time
                and (t[1:] > t[:-1]).all()
            ):
                index = np.cumsum(step, dtype=np.uint64)
                index += np.uint64(self._index)
                last = int(index[-1])
                self.counters["lost"] += last - self._index - k
                self._last_raw, self._index = int(raw[-1]), last
                self._last_time = float(t[-1])
                self._pending.append(_Accepted(index, block, self._temperature))
                self._n_pending += k
                self.counters["frames"] += k
                self._last_positions = block.positions[-1]
                return
        for fr in block.frames():
            self.frame(fr)

    def _open(self) -> None:
        ids: dict[int, None] = {}
        for _, _, fr, _ in self._pending:
            for i in fr.led_ids.tolist():
                ids.setdefault(int(i), None)
        self.led_ids = np.asarray(list(ids), np.int64)
        self._col_of = {i: j for j, i in enumerate(ids)}
        try:
            self.appender = self.appender_factory(
                self.path,
                self.led_ids,
                attrs={"source": "device", **self.attrs},
                with_status=True,
                with_temperature=True,
                overwrite=self.overwrite,
                compression=self.compression,
            )
        except OSError as e:
            if _is_disk_full(e):
                raise DiskFull(str(e)) from e
            raise UserError(f"cannot create {self.path}: {e}") from None

    def _pack(self, items: list):
        """The pending items as arrays (time, frame_index, positions, status, temperature)."""
        pieces, frames = [], []
        for it in items:
            if isinstance(it, _Accepted):
                if frames:
                    pieces.append(self._pack_frames(frames))
                    frames = []
                pieces.append(self._pack_block(it))
            else:
                frames.append(it)
        if frames:
            pieces.append(self._pack_frames(frames))
        if len(pieces) == 1:
            return pieces[0]
        return tuple(np.concatenate(arrays) for arrays in zip(*pieces, strict=True))

    def _pack_block(self, acc: _Accepted):
        b = acc.frames
        k = len(b)
        temp = np.full(k, acc.temperature, np.float32)
        ids = b.led_ids
        if ids.shape[1] == self.led_ids.shape[0] and np.all(ids == self.led_ids):
            return b.device_time, acc.index, b.positions, b.status, temp
        _, _, pos, status, _ = self._pack_frames(
            [(0, 0.0, fr, 0.0) for fr in b.frames()]  # other LEDs: placed column by column
        )
        return b.device_time, acc.index, pos, status, temp

    def _pack_frames(self, items: list[tuple[int, float, LedFrame, float]]):
        k = len(items)
        m = int(self.led_ids.shape[0])
        index = np.fromiter((it[0] for it in items), np.uint64, k)
        t = np.fromiter((it[1] for it in items), np.float64, k)
        temp = np.fromiter((it[3] for it in items), np.float32, k)
        frames = [it[2] for it in items]
        if all(fr.led_ids.shape[0] == m for fr in frames):
            # concatenate then reshape: a third of np.stack's cost on many small arrays
            ids = np.concatenate([fr.led_ids for fr in frames]).reshape(k, m)
            if np.all(ids == self.led_ids):
                pos = np.concatenate([fr.positions for fr in frames]).reshape(k, m, 3)
                status = np.concatenate([fr.status for fr in frames]).reshape(k, m)
                return t, index, pos, status.astype(np.uint8, copy=False), temp
        pos = np.full((k, m, 3), np.nan)
        status = np.ones((k, m), np.uint8)
        for j, fr in enumerate(frames):
            for i, p, s in zip(fr.led_ids.tolist(), fr.positions, fr.status.tolist()):
                col = self._col_of.get(int(i))
                if col is None:
                    self.unknown_led_ids.add(int(i))
                    self.counters["unknown_led_values"] += 1
                    continue
                pos[j, col] = p
                status[j, col] = s
        return t, index, pos, status, temp

    def write(self) -> None:
        """Append what is pending and flush (a no-op until the LED set is known).

        `threaded`: packing, compression and the flush run in a writer thread, so that
        reading the port never waits for them; an error of that thread (`DiskFull`) is
        raised by the next call. Otherwise they run here."""
        self._raise_error()
        if self.appender is None or not self._pending:
            return
        items, self._pending, self._n_pending = self._pending, [], 0
        if not self.threaded:
            self._write_items(items)
            return
        if self._thread is None:
            self._thread = threading.Thread(target=self._writer_loop, name="writer", daemon=True)
            self._thread.start()
        self._queue.put(items)

    def _raise_error(self) -> None:
        if self._error is not None:
            raise self._error

    def _writer_loop(self) -> None:
        while (items := self._queue.get()) is not None:
            if self._error is not None:
                continue  # stopped: what follows a failed write is not written
            try:
                self._write_items(items)
            except BaseException as e:  # noqa: BLE001 - handed to the reading thread
                self._error = e

    def _join(self) -> None:
        """Wait until the writer thread has written everything queued, and end it."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None

    def _write_items(self, items: list) -> None:
        t, index, pos, status, temp = self._pack(items)
        full: DiskFull | None = None
        with _quiet_stderr_fd():  # h5py prints tracebacks of freed objects after a failed write
            try:
                self.appender.append(t, index, pos, status, temp)
                self.appender.flush()
            except (OSError, RuntimeError) as e:  # h5py reports a failed flush as RuntimeError
                if not _is_disk_full(e):
                    raise
                m = re.search(r"error message = '([^']+)'", str(e))
                full = DiskFull(m.group(1) if m else str(e).splitlines()[0])
                sys.unraisablehook = _ignore_unraisable  # h5py objects freed later say it again
        if full is not None:
            raise full
        self.counters["written"] += len(t)

    def close(self) -> None:
        """Write everything (creating the file now if the LED set was not fixed yet)."""
        try:
            if self.appender is None and self._pending:
                self._open()
            self.write()
            self._join()
            self._raise_error()
        except DiskFull:
            self.abandon(close=False)
            raise
        finally:
            self.abandon()

    def abandon(self, close: bool = True) -> None:
        """Stop writing. After a failed write (`close=False`) the HDF5 file is not touched
        again (closing it after a failed flush can crash the HDF5 library): it is kept
        open in `ABANDONED`; on disk stays what the last successful flush wrote (and of
        the failed one what `read_recording` drops, as after a kill)."""
        self._join()
        if self.appender is not None:
            if close:
                try:
                    self.appender.close()
                except Exception:  # noqa: BLE001 - what was flushed stays
                    pass
            else:
                ABANDONED.append(self.appender)
            self.appender = None


# ----------------------------------------------------------------------------- the port


class Port:
    """A pyserial URL opened for reading with a `read(timeout)` that never loses bytes.

    pyserial's socket handler drops the bytes of a `read` call in which the peer closes,
    so sockets and POSIX ports are read through their file descriptor.
    """

    def __init__(self, url: str, baudrate: int = 921600) -> None:
        import serial

        self.url = url
        try:
            self.ser = serial.serial_for_url(url, baudrate=baudrate, timeout=0.05, do_not_open=True)
            # pyserial purges the input on open: that would discard the first frames a device
            # streams as soon as it is connected
            self.ser.reset_input_buffer = lambda: None
            self.ser._reset_input_buffer = lambda: None
            self.ser.open()
        except (serial.SerialException, OSError, ValueError) as e:
            raise ConnectionLost(str(e)) from None
        sock = getattr(self.ser, "_socket", None)
        self._sock = sock
        self._fd: int | None = None
        if sock is None:
            try:
                self._fd = self.ser.fileno()
            except Exception:  # noqa: BLE001 - loop://, rfc2217://, ...: no descriptor
                self._fd = None

    def read(self, timeout: float) -> bytes:
        import serial

        if self._sock is not None:
            ready, _, _ = select.select([self._sock], [], [], timeout)
            if not ready:
                return b""
            try:
                data = self._sock.recv(65536)
            except OSError as e:
                raise ConnectionLost(str(e)) from None
            if not data:
                raise ConnectionLost("the device closed the connection")
            return data
        if self._fd is not None:
            ready, _, _ = select.select([self._fd], [], [], timeout)
            if not ready:
                return b""
            try:
                data = os.read(self._fd, 65536)
            except BlockingIOError:
                return b""
            except OSError as e:
                raise ConnectionLost(e.strerror or str(e)) from None
            if not data:
                raise ConnectionLost("the device hung up")
            return data
        try:
            waiting = self.ser.in_waiting
            return self.ser.read(waiting or 1)
        except (serial.SerialException, OSError) as e:
            raise ConnectionLost(str(e)) from None

    def close(self) -> None:
        if self._sock is not None:  # pyserial's socket close sleeps 0.3 s "for the server"
            self._sock.close()
            self.ser._socket = None
            self.ser.is_open = False
            return
        try:
            self.ser.close()
        except Exception:  # noqa: BLE001 - closing a port that already went away
            pass


# ----------------------------------------------------------------------------- recorder


class Recorder:
    """Record from `port` (a pyserial URL) into `output` until end of stream, `duration`
    [s, wall clock], `request_stop()` (SIGINT/SIGTERM) or a full disk.

    `run()` returns the summary dict; ``stop_reason`` is ``"end_of_stream"``,
    ``"duration"``, ``"stopped"``, ``"connection_lost"`` or ``"disk_full"``.
    """

    def __init__(
        self,
        port: str,
        output: str | os.PathLike,
        *,
        protocol: str = "robtraj",
        duration: float | None = None,
        force: bool = False,
        reconnect_timeout: float = 30.0,
        write_interval: float = 0.5,
        batch_interval: float = 0.01,
        led_set_seconds: float = 0.5,
        progress: Any = sys.stderr,
        appender_factory: Callable[..., Any] = RecordingAppender,
        compression: str | None = "gzip",
    ) -> None:
        self.port_url = port
        self.output = Path(output)
        self.protocol = protocol
        self.duration = duration
        self.force = force
        self.reconnect_timeout = reconnect_timeout
        self.write_interval = write_interval
        self.batch_interval = batch_interval
        self.progress = progress
        if self.output.exists() and not force:
            raise UserError(f"{self.output} exists; refusing to overwrite it (use --force)")
        if not self.output.parent.is_dir():
            raise UserError(f"{self.output.parent}: no such directory")
        self.decoder = make_decoder(protocol)
        if hasattr(self.decoder, "blocks"):
            self.decoder.blocks = True  # frames as arrays (`LedFrames`), see FrameWriter.frames
        self.writer = FrameWriter(
            self.output,
            overwrite=force,
            attrs={"port": port, "protocol": protocol},
            led_set_seconds=led_set_seconds,
            appender_factory=appender_factory,
            compression=compression,
        )
        self.reconnects = 0
        self._stop = False
        self._is_tty = bool(progress is not None and getattr(progress, "isatty", lambda: False)())

    def request_stop(self) -> None:
        self._stop = True

    # ----------------------------------------------------------------- pieces

    def _handle(self, events: list) -> bool:
        """Pass events to the writer; True when the device ended the stream."""
        ended = False
        for ev in events:
            if isinstance(ev, LedFrames):
                self.writer.frames(ev)
            elif isinstance(ev, LedFrame):
                self.writer.frame(ev)
            elif isinstance(ev, StatusMessage):
                self.writer.status(ev)
            elif isinstance(ev, EndOfStream):
                ended = True
        return ended

    def _finish_decoder(self) -> bool:
        finish = getattr(self.decoder, "finish", None)
        return self._handle(finish()) if finish is not None else False

    def _reconnect(self) -> Port | None:
        delay = 0.05
        give_up = time.monotonic() + self.reconnect_timeout
        while not self._stop:
            try:
                port = Port(self.port_url)
            except ConnectionLost:
                if time.monotonic() + delay > give_up:
                    return None
                end = time.monotonic() + delay
                while time.monotonic() < end and not self._stop:
                    time.sleep(0.01)
                delay = min(2 * delay, 1.0)
                continue
            self.reconnects += 1
            return port
        return None

    def corrupted(self) -> int:
        c = self.decoder.counters
        return int(c.get("resyncs", 0) + c.get("malformed", 0))

    def _progress(self, now: float, t_start: float, last: list) -> None:
        if self.progress is None:
            return
        interval = 0.5 if self._is_tty else 2.0
        if now - last[0] < interval:
            return
        frames = self.writer.counters["frames"]
        fps = (frames - last[1]) / (now - last[0]) if last[0] else 0.0
        last[:] = [now, frames]
        m = self.writer.n_leds
        line = (
            f"{now - t_start:7.1f} s  {frames} frames  {fps:7.1f} frames/s  "
            f"LEDs seen {self.writer.leds_seen}/{m if m is not None else '?'}  "
            f"lost {self.writer.counters['lost']}  corrupted {self.corrupted()}  "
            f"reconnects {self.reconnects}"
        )
        if self._is_tty:
            self.progress.write("\r" + line + "\x1b[K")
        else:
            self.progress.write(line + "\n")
        self.progress.flush()

    # ----------------------------------------------------------------- main loop

    def run(self) -> dict[str, Any]:
        try:
            port: Port | None = Port(self.port_url)
        except ConnectionLost as e:
            raise UserError(f"cannot open port {self.port_url}: {e}") from None
        t_start = time.monotonic()
        t_first_data: float | None = None
        last_write = t_start
        last_progress = [0.0, 0]
        reason = "stopped"
        message = ""
        try:
            while True:
                if self._stop:
                    reason = "stopped"
                    break
                now = time.monotonic()
                if self.duration is not None and t_first_data is not None:
                    if now - t_first_data >= self.duration:
                        reason = "duration"
                        break
                try:
                    data = port.read(0.05)
                except ConnectionLost as e:
                    port.close()
                    port = None
                    if self._finish_decoder():
                        reason = "end_of_stream"
                        break
                    message = str(e)
                    port = self._reconnect()
                    if port is None:
                        if not self._stop:
                            reason = "connection_lost"
                        break
                    continue
                if data:
                    if t_first_data is None:
                        t_first_data = now
                    if self._handle(self.decoder.feed(data)):
                        reason = "end_of_stream"
                        break
                now = time.monotonic()
                if now - last_write >= self.write_interval or self.writer.pending >= 20000:
                    self.writer.write()
                    last_write = now
                self._progress(now, t_start, last_progress)
                if data and len(data) < 16384:
                    # a trickle (1 kHz frames arrive one by one): let bytes pile up a little,
                    # which costs nothing in latency and saves most per-wakeup overhead
                    time.sleep(self.batch_interval)
            self.writer.close()
        except DiskFull as e:
            self.writer.abandon(close=False)
            reason = "disk_full"
            message = str(e)
        except BaseException:
            self.writer.abandon()
            raise
        finally:
            if port is not None:
                port.close()
            if self.progress is not None and self._is_tty:
                self.progress.write("\n")
        return self.summary(reason, message, time.monotonic() - t_start)

    def summary(self, reason: str, message: str, wall_s: float) -> dict[str, Any]:
        w = self.writer
        return {
            "path": str(self.output),
            "port": self.port_url,
            "protocol": self.protocol,
            "stop_reason": reason,
            "message": message,
            "wall_s": wall_s,
            "led_ids": [] if w.led_ids is None else w.led_ids.tolist(),
            "unknown_led_ids": sorted(w.unknown_led_ids),
            "reconnects": self.reconnects,
            "corrupted": self.corrupted(),
            **w.counters,
            "decoder": dict(self.decoder.counters),
        }


def format_summary(s: dict[str, Any]) -> str:
    frames = s["frames"]
    lost = s["lost"]
    total = frames + lost
    pct = 100.0 * lost / total if total else 0.0
    lines = [
        f"recorded {s['written']} frames x {len(s['led_ids'])} LEDs to {s['path']} "
        f"({s['stop_reason'].replace('_', ' ')})",
        f"lost {lost} frames ({pct:.2f} %), {s['corrupted']} corrupted stretches "
        f"({s['decoder'].get('bytes_skipped', s['decoder'].get('resync_bytes', 0))} bytes "
        f"skipped), {s['reconnects']} reconnects, {s['out_of_order']} out of order",
    ]
    if s["unknown_led_ids"]:
        lines.append(
            f"LED ids first reported after the LED set was fixed (not recorded): "
            f"{s['unknown_led_ids']}"
        )
    return "\n".join(lines)
