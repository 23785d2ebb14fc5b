"""Emulator and recorder in one process over a real loopback socket, one fault at a time."""

from __future__ import annotations

import errno
import threading

import numpy as np
import pytest
from acq_helpers import check_against_ledger, synthetic_recording

from acquisition import protocol as proto
from acquisition.emulator import Emulator, Faults, SocketTransport, parse_faults
from acquisition.events import LedFrame, LedFrames, StatusMessage
from acquisition.recorder import FrameWriter, Recorder
from robtraj import UserError
from robtraj.recording import RecordingAppender, read_recording, write_recording


@pytest.fixture(scope="module")
def src():
    return synthetic_recording(n=2000)


def _run(src, tmp_path, faults: Faults, seed: int = 0, client_timeout: float = 10.0, **recorder_kw):
    transport = SocketTransport("127.0.0.1", 0)
    emulator = Emulator(
        src, transport, faults=faults, seed=seed, rate=0.0, client_timeout=client_timeout
    )
    result: dict = {}

    def serve():
        try:
            result["ledger"] = emulator.run()
        finally:
            transport.close()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    out = tmp_path / "out.h5"
    rec = Recorder(transport.url, out, progress=None, reconnect_timeout=5.0, **recorder_kw)
    summary = rec.run()
    thread.join(10)
    assert not thread.is_alive()
    return out, result["ledger"], summary


FAULTS = {
    "none": "",
    "corrupt": "corrupt=0.03",
    "truncate": "truncate=0.03",
    "drop": "drop=0.03",
    "burst": "burst=0.01",
    "noise": "noise=0.05",
    "disconnect": "disconnect=0.6",
}


@pytest.mark.parametrize("kind", list(FAULTS))
def test_each_fault_kind_against_the_ledger(src, tmp_path, kind):
    out, ledger, summary = _run(src, tmp_path, parse_faults(FAULTS[kind]), seed=7)
    assert summary["stop_reason"] == "end_of_stream"
    fates = ledger["messages"]["fate"]
    if kind == "none":
        assert set(fates) == {"intact"}
    elif kind == "noise":
        assert sum(n > 0 for n in ledger["messages"]["noise"]) > 0
    elif kind == "burst":
        assert "corrupted" in fates
    else:
        assert {"corrupt": "corrupted", "truncate": "truncated", "drop": "dropped"}.get(
            kind, kind
        ) in fates
    check_against_ledger(src, out, ledger, summary)
    if kind == "disconnect":
        assert summary["reconnects"] == fates.count("disconnect") >= 2
    rec = read_recording(out)
    assert rec.attrs["source"] == "device"
    # the u32 counter wrapped during the recording and was unwrapped
    assert rec.frame_index[-1] > 2**32


def test_fault_spec_parsing():
    f = parse_faults("corrupt=0.01, truncate=0.005,drop=0.01,disconnect=1.5,burst=0.002")
    assert (f.corrupt, f.truncate, f.drop, f.disconnect, f.burst) == (0.01, 0.005, 0.01, 1.5, 0.002)
    for bad in ("corrupt", "bogus=1", "drop=2", "corrupt=x", "disconnect=-1"):
        with pytest.raises(UserError):
            parse_faults(bad)


def test_force_overwrites_and_refuses_without(src, tmp_path):
    out = tmp_path / "out.h5"
    out.write_bytes(b"precious")
    with pytest.raises(UserError, match="exists"):
        Recorder("socket://127.0.0.1:1", out, progress=None)
    assert out.read_bytes() == b"precious"
    out2, ledger, summary = _run(src, tmp_path, Faults(), force=True)
    assert out2 == out
    check_against_ledger(src, out, ledger, summary)


class _FullDisk(RecordingAppender):
    """An appender whose disk fills up after `budget` successful appends."""

    budget = 3

    def append(self, *a, **kw):
        if _FullDisk.budget <= 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        _FullDisk.budget -= 1
        super().append(*a, **kw)


def test_full_disk_stops_cleanly_and_keeps_what_was_written(src, tmp_path):
    _FullDisk.budget = 3
    out, ledger, summary = _run(
        src,
        tmp_path,
        Faults(),
        appender_factory=_FullDisk,
        led_set_seconds=0.1,
        write_interval=0.0,
        client_timeout=0.5,
    )
    assert summary["stop_reason"] == "disk_full"
    assert "No space left" in summary["message"]
    from acquisition.recorder import ABANDONED

    assert len(ABANDONED) == 1
    ABANDONED.pop().close()  # a real full disk leaves it to process exit
    rec = read_recording(out)
    assert rec.n_frames == summary["written"] > 0
    assert summary["written"] < src.n_frames
    np.testing.assert_array_equal(
        np.float32(rec.positions * 1e3), np.float32(src.positions[: rec.n_frames] * 1e3)
    )


def _frame(counter: int, t: float, ids, seen=None) -> LedFrame:
    ids = np.asarray(ids)
    pos = np.arange(3 * len(ids), dtype=np.float64).reshape(-1, 3) + counter
    status = np.zeros(len(ids), np.uint8)
    return LedFrame(counter, t, ids, pos, status)


def test_led_set_from_first_half_second_and_late_ids_counted(tmp_path):
    w = FrameWriter(tmp_path / "r.h5", led_set_seconds=0.5)
    w.frame(_frame(0, 0.0, [5, 6]))
    w.frame(_frame(1, 0.1, [6, 9]))  # 9 appears within the first 0.5 s: a column
    w.frame(_frame(2, 0.6, [5, 6, 9]))  # fixes the set
    w.frame(_frame(3, 0.7, [5, 11]))  # 11 is new after the set was fixed
    w.frame(_frame(2**32 + 1, 0.8, [5, 6, 9]))  # counter jumps by 2**32 - 2: out of order
    w.frame(_frame(5, 0.7, [5, 6, 9]))  # time does not increase
    w.frame(_frame(7, 0.9, [9, 6, 5]))  # other order; 3 lost frames (4, 5, 6)
    w.close()
    rec = read_recording(tmp_path / "r.h5")
    np.testing.assert_array_equal(rec.led_ids, [5, 6, 9])
    np.testing.assert_array_equal(rec.frame_index, [0, 1, 2, 3, 7])
    assert np.isnan(rec.positions[0, 2]).all() and rec.status[0, 2] == 1
    np.testing.assert_array_equal(rec.positions[1, 1], [1, 2, 3])
    np.testing.assert_array_equal(rec.positions[4, 0], [13, 14, 15])
    assert w.unknown_led_ids == {11} and w.counters["unknown_led_values"] == 1
    assert w.counters["lost"] == 3
    assert w.counters["out_of_order"] == 1 and w.counters["non_monotonic_time"] == 1
    assert np.isnan(rec.temperature).all()


def _blocks(seed: int) -> list:
    """Blocks of frames as a decoder gives them, with status messages between them, and
    all the irregular cases: counter wrap, gaps, repeats, backward steps, times that do
    not increase, other LED sets and sizes."""
    rng = np.random.default_rng(seed)
    ids = np.array([4, 7, 9, 12])
    counter, t, events = 2**32 - 300, 1.0, []
    for j in range(40):
        k = int(rng.integers(1, 40))
        step = np.ones(k, np.int64)
        odd = rng.random(k)
        step[odd < 0.05] = rng.integers(2, 50)  # lost frames
        step[odd > 0.97] = 0  # a repeat
        step[(odd > 0.95) & (odd <= 0.97)] = -3  # backwards
        counters = counter + np.cumsum(step)
        counter = int(counters[-1])
        dt = np.full(k, 1e-3)
        dt[rng.random(k) < 0.03] = -2e-3  # time going back
        times = t + np.cumsum(dt)
        t = float(times[-1])
        block_ids = np.tile(ids, (k, 1))
        if j > 5 and rng.random() < 0.15:  # another LED set (unknown id, other order, fewer)
            block_ids = np.tile(
                rng.choice([4, 7, 9, 12, 30], size=int(rng.integers(1, 5)), replace=False), (k, 1)
            )
        n = block_ids.shape[1]
        status = rng.integers(0, 4, (k, n)).astype(np.uint8)
        pos = rng.normal(size=(k, n, 3))
        pos[status == 1] = np.nan
        events.append(LedFrames(counters % 2**32, times, block_ids, pos, status))
        if rng.random() < 0.5:
            events.append(StatusMessage(t, float(rng.normal(24.0, 1.0))))
    return events


@pytest.mark.parametrize("seed", range(5))
def test_blocks_are_written_as_their_frames_one_by_one(tmp_path, seed):
    """`FrameWriter.frames` (whole blocks where it can) gives the rows and counters that
    `frame` gives for the same frames one by one."""
    events = _blocks(seed)
    writers = {}
    for how in ("blocks", "frames"):
        w = writers[how] = FrameWriter(tmp_path / f"{how}.h5", led_set_seconds=0.05)
        for i, ev in enumerate(events):
            if isinstance(ev, StatusMessage):
                w.status(ev)
            elif how == "blocks":
                w.frames(ev)
            else:
                for fr in ev.frames():
                    w.frame(fr)
            if i % 7 == 6:
                w.write()
        w.close()
    assert writers["blocks"].counters == writers["frames"].counters
    assert writers["blocks"].counters["lost"] > 0 and writers["blocks"].counters["out_of_order"] > 0
    assert writers["blocks"].counters["non_monotonic_time"] > 0
    assert writers["blocks"].unknown_led_ids == writers["frames"].unknown_led_ids == {30}
    a, b = read_recording(tmp_path / "blocks.h5"), read_recording(tmp_path / "frames.h5")
    for key in ("time", "frame_index", "led_ids", "positions", "status", "temperature"):
        assert getattr(a, key).tobytes() == getattr(b, key).tobytes(), key


def test_short_stream_still_written(tmp_path):
    """A stream shorter than the LED-set window is written at close."""
    w = FrameWriter(tmp_path / "r.h5")
    for i in range(3):
        w.frame(_frame(i, 0.001 * (i + 1), [1, 2]))
    w.close()
    assert read_recording(tmp_path / "r.h5").n_frames == 3


def test_recorder_reads_loop_url(tmp_path):
    """Any pyserial URL: loop:// echoes what is written to it (no file descriptor)."""
    from acquisition.recorder import Port

    port = Port("loop://")
    wire = proto.encode_status(1, 20.0)
    port.ser.write(wire)
    assert port.read(0.05) == wire
    port.close()


def test_emulator_refuses_ids_beyond_u8(tmp_path):
    rec = synthetic_recording(n=10, m=2)
    rec = rec.replace(led_ids=np.array([1, 300], np.int32))
    from acquisition.emulator import DeviceStream

    with pytest.raises(UserError, match="ids 0..255"):
        DeviceStream(rec)
    write_recording(rec, tmp_path / "x.h5")


def test_duration_stops_the_recording(src, tmp_path):
    transport = SocketTransport("127.0.0.1", 0)
    emulator = Emulator(src, transport, rate=1000.0, client_timeout=0.5)
    thread = threading.Thread(target=emulator.run, daemon=True)
    thread.start()
    try:
        out = tmp_path / "out.h5"
        summary = Recorder(transport.url, out, progress=None, duration=0.8).run()
    finally:
        thread.join(10)
        transport.close()
    assert summary["stop_reason"] == "duration"
    rec = read_recording(out)
    assert 300 < rec.n_frames == summary["written"] < src.n_frames
    np.testing.assert_array_equal(rec.frame_index, src.frame_index[: rec.n_frames])


def test_port_keeps_the_bytes_sent_while_it_opens(monkeypatch):
    """A device streams from the moment the connection exists; what arrives while the port
    is still being opened (pyserial purges its input at the end of `open`) is kept."""
    import socket
    import time

    import serial.urlhandler.protocol_socket as ps

    from acquisition.recorder import ConnectionLost, Port

    configure = ps.Serial._reconfigure_port

    def slow_configure(self, *a, **k):  # the bytes are there before open() ends
        time.sleep(0.2)
        return configure(self, *a, **k)

    monkeypatch.setattr(ps.Serial, "_reconfigure_port", slow_configure)
    payload = bytes(range(256)) * 4
    listener = socket.create_server(("127.0.0.1", 0))

    def serve():
        conn, _ = listener.accept()
        conn.sendall(payload)
        conn.close()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    port = Port(f"socket://127.0.0.1:{listener.getsockname()[1]}")
    got = b""
    with pytest.raises(ConnectionLost):
        while True:
            got += port.read(1.0)
    port.close()
    listener.close()
    assert got == payload


@pytest.mark.parametrize("seeds", [range(20)])
def test_every_intact_frame_recorded_over_20_fault_seeds(tmp_path, seeds):
    """Every fault at once, 20 seeds, short streams with 2-3 reconnects each: the recording
    holds exactly the frames the emulator's ledger says arrived intact, including the first
    one of every connection."""
    src = synthetic_recording(n=700, seed=3)
    faults = parse_faults(
        "corrupt=0.02,truncate=0.02,drop=0.02,burst=0.005,noise=0.02,disconnect=0.25"
    )
    for seed in seeds:
        d = tmp_path / str(seed)
        d.mkdir()
        out, ledger, summary = _run(src, d, faults, seed=seed)
        assert summary["stop_reason"] == "end_of_stream", (seed, summary)
        msgs = ledger["messages"]
        assert summary["reconnects"] == msgs["fate"].count("disconnect") >= 2, seed
        check_against_ledger(src, out, ledger, summary)
        # the first intact frame after each (re)connection, explicitly
        firsts = {}
        for k, i, f, c in zip(msgs["kind"], msgs["index"], msgs["fate"], msgs["connection"]):
            if k == "frame" and f == "intact":
                firsts.setdefault(c, i)
        recorded = set(np.asarray(read_recording(out).frame_index, np.int64).tolist())
        fi = np.asarray(src.frame_index, np.int64)
        assert all(int(fi[i]) in recorded for i in firsts.values()), seed
