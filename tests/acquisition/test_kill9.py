"""`robtraj record` killed with SIGKILL at 10 moments: each file opens with plain h5py and
`read_recording`, and holds every frame the emulator had sent up to 1 s before the kill."""

from __future__ import annotations

import os
import signal
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import h5py
import numpy as np
from acq_helpers import popen, synthetic_recording

from acquisition.emulator import Emulator, SocketTransport
from robtraj.recording import read_recording

KILL_AFTER_S = np.linspace(1.5, 6.0, 10)  # after the emulator sent the first frame
MAX_LOSS_S = 1.0  # frames sent earlier than this before the kill must be in the file
PARALLEL = 3  # recorder processes at once (each needs ~10 % of a core at 1000 Hz)


class _OneRecorder(SocketTransport):
    """Loopback transport that serves the first recorder only: once it is gone (killed),
    the emulator does not wait for another and its stream ends."""

    def __init__(self) -> None:
        super().__init__("127.0.0.1", 0)
        self._served = False

    def wait_client(self, timeout: float) -> bool:
        if self._served:
            return False
        self._served = super().wait_client(timeout)
        return self._served


class _ClockedEmulator(Emulator):
    """Keeps the monotonic time at which each LED frame had gone out whole: `_log` is
    called once `sendall` returned for the batch holding the frame."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.sent: list[tuple[float, int]] = []  # (time.monotonic(), row of the recording)

    def _log(self, msg, fate: str, noise: int = 0) -> None:
        super()._log(msg, fate, noise)
        if msg.kind == "frame" and fate == "intact":
            self.sent.append((time.monotonic(), msg.index))


def _record_and_kill(src, out, kill_after: float) -> dict:
    """Emulator (1000 Hz, in a thread) -> `robtraj record` (a process), SIGKILL
    `kill_after` s after the first frame went out; what was sent and when."""
    transport = _OneRecorder()
    emulator = _ClockedEmulator(src, transport, client_timeout=60.0)
    failure: list[BaseException] = []

    def serve() -> None:
        try:
            emulator.run()
        except BaseException as e:  # noqa: BLE001 - reported by the test
            failure.append(e)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    rec = popen("record", "--port", transport.url, "-o", str(out), "--quiet")
    try:
        deadline = time.monotonic() + 60.0
        while not emulator.sent:
            assert rec.poll() is None, rec.communicate()
            assert time.monotonic() < deadline, "the recorder did not connect"
            time.sleep(0.005)
        time.sleep(max(0.0, emulator.sent[0][0] + kill_after - time.monotonic()))
        t_kill = time.monotonic()
        os.kill(rec.pid, signal.SIGKILL)
        rec.communicate(timeout=10)
    finally:
        if rec.returncode is None:
            rec.kill()
            rec.communicate(timeout=10)
        thread.join(10)
        transport.close()
    assert rec.returncode == -signal.SIGKILL, "the recorder ended before it was killed"
    assert not thread.is_alive() and not failure, failure
    sent = np.array(emulator.sent)
    return {"t_kill": t_kill, "sent_time": sent[:, 0], "sent_row": sent[:, 1].astype(int)}


def _check(src, out, run: dict, kill_after: float) -> dict:
    with h5py.File(out, "r") as f:  # plain h5py: no SWMR, no h5clear
        assert "tracker/time" in f and "tracker/positions" in f
    got = read_recording(out)
    k = got.n_frames
    # a prefix of the stream, exactly: nothing invented, reordered or altered
    np.testing.assert_array_equal(got.frame_index, src.frame_index[:k])
    np.testing.assert_array_equal(got.time, np.round(src.time[:k] * 1e6) / 1e6)
    np.testing.assert_array_equal(
        np.float32(got.positions * 1e3), np.float32(src.positions[:k] * 1e3)
    )
    np.testing.assert_array_equal(got.status, src.status[:k])
    t_sent, rows = run["sent_time"], run["sent_row"]
    np.testing.assert_array_equal(rows, np.arange(rows.size))  # sent in order, none damaged
    t_kill = run["t_kill"]
    due = int(np.count_nonzero(t_sent <= t_kill - MAX_LOSS_S))
    sent_by_kill = int(np.count_nonzero(t_sent <= t_kill))
    # how long before the kill the oldest frame missing from the file had been sent
    oldest_missing_s = t_kill - t_sent[k] if k < rows.size else 0.0
    stats = {
        "kill_after_s": round(kill_after, 2),
        "sent_by_kill": sent_by_kill,
        "recorded": k,
        "missing": sent_by_kill - k,
        "oldest_missing_sent_s_before_kill": round(float(oldest_missing_s), 3),
    }
    assert k >= due, f"frames sent more than {MAX_LOSS_S} s before the kill are missing: {stats}"
    return stats


def test_sigkill_at_10_moments_loses_at_most_the_last_second(tmp_path):
    src = synthetic_recording(n=8000)  # 8 s at 1000 Hz, 18 LEDs, counter wraps
    t0 = time.monotonic()

    def one(i: int) -> dict:
        d = tmp_path / f"kill{i}"
        d.mkdir()
        run = _record_and_kill(src, d / "out.h5", float(KILL_AFTER_S[i]))
        return _check(src, d / "out.h5", run, float(KILL_AFTER_S[i]))

    with ThreadPoolExecutor(PARALLEL) as pool:
        stats = list(pool.map(one, range(KILL_AFTER_S.size)))
    print(f"\n{len(stats)} kills in {time.monotonic() - t0:.1f} s")
    for s in stats:
        print("  ", s)
