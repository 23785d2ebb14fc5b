"""Device emulator: replay a recording as the tracker would stream it, with injected faults.

The emulator serves the robtraj protocol (PROTOCOL.md) on a real TCP socket on loopback
(`socket://HOST:PORT`, it listens, the recorder connects) or on a real pseudo-terminal
(`pty`, or `pty:LINK` to keep a symlink `LINK` pointing at the current slave device, so a
recorder can reopen the same path after an emulated cable pull). Frames go out at the
recording's rate (or `rate`), carrying `/tracker/frame_index` as the (wrapping) counter
and `/tracker/time` as device time; a status message with the camera temperature
precedes every tenth of a second of frames when the recording has temperature; an
end-of-stream message closes the stream.

Faults (``--faults``, comma separated ``name=value``; probabilities are per message):

- ``corrupt=P``: flip 1 to 3 random bits of the message (always caught by the CRCs).
- ``truncate=P``: send only a random proper prefix of the message.
- ``drop=P``: do not send the message (a counter gap for LED frames).
- ``burst=P``: a noise burst of 8 to 64 bytes overwrites the stream from a random point
  in the message on, possibly into the following messages (every one touched is damaged).
- ``noise=P``: 8 to 64 random bytes are inserted on the line before the message.
- ``disconnect=S``: every S seconds of recording time the connection drops in the middle
  of a message; the emulator then waits for the recorder to reconnect. Paced frames whose
  time passes while nobody is connected are lost, as they would be on a real device.

The ledger (`ledger`, written as JSON) lists every message in order with its fate:
``intact``, ``dropped``, ``truncated``, ``corrupted``, ``disconnect`` (cut by a
disconnect), ``lost_disconnected`` (produced while no recorder was connected) or
``unsent`` (the recorder went away for good); ``noise`` gives the bytes inserted before
it and ``connection`` the connection it went out on.
"""

from __future__ import annotations

import dataclasses
import json
import os
import select
import socket
import time
import tty
from pathlib import Path
from typing import Any

import numpy as np

from robtraj import UserError
from robtraj.recording import Recording

from . import protocol

FAULT_NAMES = ("corrupt", "truncate", "drop", "burst", "noise", "disconnect")
DAMAGED = frozenset({"truncated", "corrupted", "disconnect"})
LOST = frozenset({"dropped", "truncated", "corrupted", "disconnect", "lost_disconnected", "unsent"})


@dataclasses.dataclass(frozen=True)
class Faults:
    """Fault rates: probabilities per message, `disconnect` a period [s] (0 = never)."""

    corrupt: float = 0.0
    truncate: float = 0.0
    drop: float = 0.0
    burst: float = 0.0
    noise: float = 0.0
    disconnect: float = 0.0

    def as_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


def parse_faults(spec: str | None) -> Faults:
    """Parse ``"corrupt=0.01,drop=0.01,disconnect=1.5"``; `UserError` on anything else."""
    if not spec:
        return Faults()
    values: dict[str, float] = {}
    for item in spec.split(","):
        item = item.strip()
        if not item:
            continue
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in FAULT_NAMES:
            raise UserError(
                f"bad fault {item!r} in --faults; use NAME=VALUE with NAME one of "
                f"{', '.join(FAULT_NAMES)}"
            )
        try:
            v = float(value)
        except ValueError:
            raise UserError(f"bad fault value {value!r} for {name}; expected a number") from None
        if not np.isfinite(v) or v < 0 or (name != "disconnect" and v > 1):
            raise UserError(
                f"fault {name}={value} out of range (probabilities in 0..1, disconnect >= 0 s)"
            )
        values[name] = v
    return Faults(**values)


# ----------------------------------------------------------------------------- messages


@dataclasses.dataclass(frozen=True)
class Message:
    kind: str  # "frame" | "status" | "end"
    index: int  # row of the recording (-1 for end of stream)
    counter: int  # frame counter as sent (frames), else -1
    wire: bytes


class DeviceStream:
    """The messages a device would send for `rec`, in order, encoded lazily."""

    def __init__(self, rec: Recording, status_rate_hz: float = 10.0) -> None:
        if rec.n_frames == 0:
            raise UserError("the recording has no tracker frames to replay")
        ids = np.asarray(rec.led_ids)
        if not np.issubdtype(ids.dtype, np.integer):
            raise UserError(f"/tracker/led_ids must be integers, not {ids.dtype}")
        if ids.size > protocol.MAX_LEDS or np.any((ids < 0) | (ids > 255)):
            raise UserError(
                "the robtraj protocol carries at most 255 LEDs with ids 0..255; "
                f"this recording has {ids.size} LEDs with ids {ids.min()}..{ids.max()}"
            )
        t = np.asarray(rec.time, np.float64)
        if t[0] < 0:
            raise UserError("/tracker/time starts below 0 s; device time must be >= 0")
        self.time = t
        self.time_us = np.round(t * 1e6).astype(np.int64)
        if np.any(np.diff(self.time_us) <= 0):
            raise UserError("/tracker/time steps below 1 µs; the device clock has µs resolution")
        self.counter = (np.asarray(rec.frame_index, np.uint64) % np.uint64(1 << 32)).astype(
            np.int64
        )
        self.led_ids = ids.astype(np.uint8)
        visible = rec.visible
        status = (
            np.zeros(visible.shape, np.uint8)
            if rec.status is None
            else np.asarray(rec.status, np.uint8).copy()
        )
        status[~visible & (status == 0)] = protocol.STATUS_MISSING
        self.status = status
        self.positions_mm = np.asarray(np.asarray(rec.positions, np.float64) * 1000.0, np.float32)
        self.positions_mm[~visible] = np.nan
        self.temperature = (
            None if rec.temperature is None else np.asarray(rec.temperature, np.float32)
        )
        dt = np.diff(t)
        self.rate = float(1.0 / np.median(dt)) if dt.size else 1.0
        self.status_every = max(1, int(round(self.rate / status_rate_hz)))
        self.n_frames = int(t.shape[0])

    def messages(self):
        for i in range(self.n_frames):
            if self.temperature is not None and i % self.status_every == 0:
                temp = float(self.temperature[i])
                if np.isfinite(temp):
                    yield Message(
                        "status", i, -1, protocol.encode_status(int(self.time_us[i]), temp)
                    )
            wire = protocol.encode_led_frame(
                int(self.counter[i]),
                int(self.time_us[i]),
                self.led_ids,
                self.positions_mm[i],
                self.status[i],
            )
            yield Message("frame", i, int(self.counter[i]), wire)


# ----------------------------------------------------------------------------- transports


class SocketTransport:
    """Listen on HOST:PORT (PORT 0 = any free port), one recorder connection at a time."""

    def __init__(self, host: str, port: int) -> None:
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._listener.bind((host, port))
        except OSError as e:
            self._listener.close()
            raise UserError(f"cannot listen on {host}:{port}: {e.strerror or e}") from None
        self._listener.listen(1)
        self.host = host
        self.port = self._listener.getsockname()[1]
        self.url = f"socket://{host}:{self.port}"
        self._conn: socket.socket | None = None

    def wait_client(self, timeout: float) -> bool:
        self._listener.settimeout(timeout)
        try:
            conn, _ = self._listener.accept()
        except TimeoutError:
            return False
        conn.setblocking(True)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._conn = conn
        return True

    def send(self, data: bytes | bytearray) -> bool:
        if self._conn is None:
            return False
        try:
            self._conn.sendall(data)
        except OSError:
            self._drop()
            return False
        return True

    def _drop(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            finally:
                self._conn = None

    def disconnect(self) -> None:
        self._drop()

    def finish(self, timeout: float) -> None:
        """After the last message: half-close, wait for the recorder to hang up."""
        if self._conn is None:
            return
        try:
            self._conn.shutdown(socket.SHUT_WR)
            self._conn.settimeout(timeout)
            while self._conn.recv(4096):
                pass
        except OSError:
            pass
        self._drop()

    def close(self) -> None:
        self._drop()
        self._listener.close()


class PtyTransport:
    """A pseudo-terminal; the recorder opens its slave device (or the symlink `link`)."""

    def __init__(self, link: str | None = None) -> None:
        self.link = link
        self._master = -1
        self._open()

    def _open(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        self.slave_path = os.ttyname(slave)
        os.close(slave)  # the master sees POLLHUP until a recorder opens the slave
        self._master = master
        if self.link:
            tmp = f"{self.link}.tmp-{os.getpid()}"
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(self.slave_path, tmp)
            os.replace(tmp, self.link)

    @property
    def url(self) -> str:
        return self.link or self.slave_path

    def _hung_up(self) -> bool:
        p = select.poll()
        p.register(self._master, select.POLLHUP)
        return any(ev & select.POLLHUP for _, ev in p.poll(0))

    def wait_client(self, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while self._hung_up():
            if time.monotonic() > end:
                return False
            time.sleep(0.01)
        return True

    def send(self, data: bytes | bytearray) -> bool:
        if self._hung_up():
            return False
        view = memoryview(data)
        try:
            while view:
                n = os.write(self._master, view)
                view = view[n:]
        except OSError:
            return False
        return True

    def _drain(self, timeout: float) -> None:
        """Wait until the recorder has read what was written (closing the master discards
        unread bytes): the slave's input queue, asked through a momentary slave descriptor."""
        import fcntl
        import termios

        end = time.monotonic() + timeout
        try:
            fd = os.open(self.slave_path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError:
            return
        try:
            buf = bytearray(4)
            empty = 0  # the tty flip buffers refill the queue as the reader reads: wait until
            while time.monotonic() < end and empty < 5:  # it stays empty for 50 ms
                fcntl.ioctl(fd, termios.FIONREAD, buf)
                empty = empty + 1 if int.from_bytes(buf, "little") == 0 else 0
                time.sleep(0.01)
        finally:
            os.close(fd)

    def disconnect(self) -> None:
        """A cable pull: close this pty (the reader gets EIO) and offer a fresh one."""
        self._drain(2.0)
        os.close(self._master)
        self._open()

    def finish(self, timeout: float) -> None:
        end = time.monotonic() + timeout
        while not self._hung_up() and time.monotonic() < end:
            time.sleep(0.02)

    def close(self) -> None:
        if self._master >= 0:
            os.close(self._master)
            self._master = -1
        if self.link and os.path.islink(self.link):
            os.unlink(self.link)


def open_transport(url: str) -> SocketTransport | PtyTransport:
    """`socket://HOST:PORT` or `pty` / `pty:LINK`."""
    if url == "pty" or url.startswith("pty:"):
        link = url[4:] or None
        return PtyTransport(link)
    if url.startswith("socket://"):
        hostport = url[len("socket://") :].split("?")[0]
        host, sep, port = hostport.rpartition(":")
        if not sep or not port.isdigit():
            raise UserError(f"bad port {url!r}; expected socket://HOST:PORT")
        return SocketTransport(host or "127.0.0.1", int(port))
    raise UserError(f"the emulator serves socket://HOST:PORT or pty[:LINK], not {url!r}")


# ----------------------------------------------------------------------------- emulator


class Emulator:
    """Replays `rec` over `transport` at `rate` [Hz] (None: the recording's; 0: unpaced)."""

    def __init__(
        self,
        rec: Recording,
        transport: SocketTransport | PtyTransport,
        *,
        faults: Faults = Faults(),
        seed: int = 0,
        rate: float | None = None,
        client_timeout: float = 30.0,
    ) -> None:
        self.stream = DeviceStream(rec)
        self.transport = transport
        self.faults = faults
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self.rate = self.stream.rate if rate is None else float(rate)
        self.client_timeout = client_timeout
        self.ledger: dict[str, list[Any]] = {
            "kind": [],
            "index": [],
            "counter": [],
            "fate": [],
            "noise": [],
            "connection": [],
        }
        self.connection = 0
        self.stop = False

    def _log(self, msg: Message, fate: str, noise: int = 0) -> None:
        led = self.ledger
        led["kind"].append(msg.kind)
        led["index"].append(msg.index)
        led["counter"].append(msg.counter)
        led["fate"].append(fate)
        led["noise"].append(noise)
        led["connection"].append(self.connection)

    def _random_bytes(self, n: int) -> bytes:
        return self.rng.integers(0, 256, n, dtype=np.uint8).tobytes()

    def _damage(self, msg: Message, burst_left: int) -> tuple[bytes | None, str, int, int]:
        """Apply the per-message faults; returns (wire or None, fate, noise bytes, burst left)."""
        f, rng = self.faults, self.rng
        noise = int(rng.integers(8, 65)) if f.noise and rng.random() < f.noise else 0
        if f.drop and rng.random() < f.drop:
            return None, "dropped", noise, burst_left
        wire = bytearray(msg.wire)
        fate = "intact"
        if f.truncate and rng.random() < f.truncate:
            wire = wire[: int(rng.integers(1, len(wire)))]
            fate = "truncated"
        elif f.corrupt and rng.random() < f.corrupt:
            for _ in range(int(rng.integers(1, 4))):
                bit = int(rng.integers(0, 8 * len(wire)))
                wire[bit // 8] ^= 1 << (bit % 8)
            if bytes(wire) != msg.wire:  # two flips of one bit cancel
                fate = "corrupted"
        start = 0
        if not burst_left and f.burst and rng.random() < f.burst:
            burst_left = int(rng.integers(8, 65))
            start = int(rng.integers(0, len(wire)))
        if burst_left and start < len(wire):
            k = min(burst_left, len(wire) - start)
            xor = self.rng.integers(1, 256, k, dtype=np.uint8)
            seg = np.frombuffer(bytes(wire[start : start + k]), np.uint8) ^ xor
            wire[start : start + k] = seg.tobytes()
            burst_left -= k
            if fate == "intact":
                fate = "corrupted"
        return bytes(wire), fate, noise, burst_left

    def run(self) -> dict[str, Any]:
        s = self.stream
        paced = self.rate > 0
        scale = (s.rate / self.rate) if paced else 0.0
        if not self.transport.wait_client(self.client_timeout):
            raise UserError(
                f"no recorder connected to {self.transport.url} within {self.client_timeout:g} s"
            )
        t0 = time.monotonic()
        t_first = s.time[0]
        conn_start = s.time[0]
        burst_left = 0
        batch = bytearray()
        pending: list[tuple[Message, str, int]] = []
        connected = True

        def flush() -> bool:
            nonlocal connected
            ok = self.transport.send(batch) if batch else True
            for m, fate, nz in pending:
                self._log(m, fate if ok else "unsent", nz)
            batch.clear()
            pending.clear()
            if not ok:
                connected = False
            return ok

        resume_at = t0  # paced messages due before this went out while nobody was connected
        for msg in s.messages():
            if self.stop:
                break
            t_msg = s.time[msg.index]
            due = t0 + (t_msg - t_first) * scale
            if paced:
                now = time.monotonic()
                if due > now:
                    flush()
                    time.sleep(due - now)
            if len(batch) > 65536:
                flush()
            if not connected:  # the recorder went away: wait for it, the device runs on
                self.connection += 1
                if not self.transport.wait_client(self.client_timeout):
                    self._log(msg, "unsent")
                    break
                connected = True
                conn_start = t_msg
                resume_at = time.monotonic()
            if paced and due < resume_at - 0.002:
                self._log(msg, "lost_disconnected")
                continue
            if self.faults.disconnect and t_msg - conn_start >= self.faults.disconnect:
                cut = int(self.rng.integers(1, len(msg.wire)))
                batch += msg.wire[:cut]
                pending.append((msg, "disconnect", 0))
                flush()
                self.transport.disconnect()
                self.connection += 1
                burst_left = 0
                if not self.transport.wait_client(self.client_timeout):
                    break
                connected = True
                conn_start = t_msg
                resume_at = time.monotonic()
                continue
            wire, fate, noise, burst_left = self._damage(msg, burst_left)
            if noise:
                batch += self._random_bytes(noise)
            if wire is not None:
                batch += wire
            pending.append((msg, fate, noise))
        end = Message("end", -1, -1, protocol.encode_end_of_stream())
        batch += end.wire
        pending.append((end, "intact", 0))
        flush()
        self.transport.finish(timeout=5.0)
        return self.result()

    def result(self) -> dict[str, Any]:
        return {
            "faults": self.faults.as_dict(),
            "seed": self.seed,
            "rate_hz": self.rate,
            "recording_rate_hz": self.stream.rate,
            "n_frames": self.stream.n_frames,
            "url": self.transport.url,
            "messages": self.ledger,
        }


def write_ledger(ledger: dict[str, Any], path: str | os.PathLike) -> None:
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(ledger))
    os.replace(tmp, path)
