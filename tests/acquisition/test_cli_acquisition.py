"""`robtraj emulate` and `robtraj record` as two processes over a real socket and a real pty."""

from __future__ import annotations

import resource
import signal
import subprocess
import time

import numpy as np
import pytest
from acq_helpers import (
    check_against_ledger,
    load_json,
    popen,
    robtraj_cmd,
    wait_for_file,
    write_synthetic,
)

from robtraj.cli import main
from robtraj.recording import read_recording

ALL_FAULTS = "corrupt=0.01,truncate=0.01,drop=0.01,burst=0.005,noise=0.01,disconnect=0.9"


def _reap(*procs: subprocess.Popen) -> None:
    for proc in procs:
        if proc.returncode is None:
            proc.kill()
            proc.communicate(timeout=10)


def _finish(proc: subprocess.Popen, timeout: float = 30.0) -> tuple[int, str, str]:
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"process did not finish: {err}") from None
    return proc.returncode, out, err


@pytest.mark.parametrize("transport", ["socket", "pty"])
def test_emulator_and_recorder_with_every_fault(tmp_path, transport):
    src = write_synthetic(tmp_path / "src.h5", n=2000)
    port = "socket://127.0.0.1:0" if transport == "socket" else f"pty:{tmp_path / 'tty'}"
    emu = popen(
        "emulate", str(tmp_path / "src.h5"), "--port", port, "--rate", "2000",
        "--faults", ALL_FAULTS, "--seed", "11",
        "--ledger", str(tmp_path / "ledger.json"), "--port-file", str(tmp_path / "port"),
    )  # fmt: skip
    try:
        url = wait_for_file(tmp_path / "port", proc=emu)
        rec = popen(
            "record", "--port", url, "-o", str(tmp_path / "out.h5"),
            "--json", str(tmp_path / "summary.json"), "--reconnect-timeout", "10",
        )  # fmt: skip
        code, _, err = _finish(rec)
        assert code == 0, err
        assert "frames/s" in err and "recorded" in err
        ecode, _, eerr = _finish(emu)
        assert ecode == 0, eerr
    finally:
        _reap(emu)
    ledger = load_json(tmp_path / "ledger.json")
    summary = load_json(tmp_path / "summary.json")
    fates = set(ledger["messages"]["fate"])
    assert {"corrupted", "truncated", "dropped", "disconnect"} <= fates
    assert any(ledger["messages"]["noise"])
    assert summary["stop_reason"] == "end_of_stream" and summary["reconnects"] >= 1
    check_against_ledger(src, tmp_path / "out.h5", ledger, summary)


def _start_pair(tmp_path, n: int = 2500):
    write_synthetic(tmp_path / "src.h5", n=n)
    emu = popen(
        "emulate", str(tmp_path / "src.h5"), "--port", "socket://127.0.0.1:0",
        "--port-file", str(tmp_path / "port"), "--client-timeout", "20",
    )  # fmt: skip
    url = wait_for_file(tmp_path / "port", proc=emu)
    rec = popen(
        "record", "--port", url, "-o", str(tmp_path / "out.h5"),
        "--json", str(tmp_path / "summary.json"),
    )  # fmt: skip
    return emu, rec


def _wait_frames(path, proc, timeout: float = 30.0) -> tuple[float, int]:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        assert proc.poll() is None, proc.communicate()
        if path.exists():
            try:
                n = read_recording(path).n_frames
            except Exception:  # noqa: BLE001 - file being created
                n = 0
            if n:
                return time.monotonic(), n
        time.sleep(0.05)
    raise AssertionError("the recorder wrote no frames")


def test_sigkill_leaves_a_readable_file(tmp_path):
    emu, rec = _start_pair(tmp_path)
    try:
        t1, n1 = _wait_frames(tmp_path / "out.h5", rec)
        time.sleep(1.5)
        t_kill = time.monotonic()
        rec.send_signal(signal.SIGKILL)
        rec.communicate(timeout=10)
    finally:
        _reap(emu, rec)
    out = read_recording(tmp_path / "out.h5")
    src = read_recording(tmp_path / "src.h5")
    # streamed by the kill: >= n1 + 1000 Hz x (t_kill - t1); at most ~1 s of it may be lost
    streamed = n1 + int(1000 * (t_kill - t1))
    assert out.n_frames >= streamed - 1000 - 100, (out.n_frames, streamed)
    k = out.n_frames
    np.testing.assert_array_equal(
        np.float32(out.positions * 1e3), np.float32(src.positions[:k] * 1e3)
    )
    np.testing.assert_array_equal(out.frame_index, src.frame_index[:k])


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_stops_cleanly(tmp_path, sig):
    emu, rec = _start_pair(tmp_path)
    try:
        _wait_frames(tmp_path / "out.h5", rec)
        time.sleep(0.3)
        rec.send_signal(sig)
        code, _, err = _finish(rec)
    finally:
        _reap(emu, rec)
    assert code == 0, err
    summary = load_json(tmp_path / "summary.json")
    assert summary["stop_reason"] == "stopped"
    out = read_recording(tmp_path / "out.h5")
    assert out.n_frames == summary["written"] == summary["frames"] > 0
    assert "Traceback" not in err


def test_full_disk_stops_with_one_line_and_keeps_the_file(tmp_path):
    """A real write failure: the recorder's file size limit (RLIMIT_FSIZE) is the full disk."""
    write_synthetic(tmp_path / "src.h5", n=2500)
    emu = popen(
        "emulate", str(tmp_path / "src.h5"), "--port", "socket://127.0.0.1:0",
        "--port-file", str(tmp_path / "port"), "--client-timeout", "20",
    )  # fmt: skip

    def limit_file_size():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a signal
        resource.setrlimit(resource.RLIMIT_FSIZE, (600_000, 600_000))

    try:
        url = wait_for_file(tmp_path / "port", proc=emu)
        p = subprocess.run(
            robtraj_cmd(
                "record",
                "--port",
                url,
                "-o",
                str(tmp_path / "out.h5"),
                "--quiet",
                "--json",
                str(tmp_path / "summary.json"),
            ),  # fmt: skip
            capture_output=True,
            text=True,
            timeout=60,
            preexec_fn=limit_file_size,
        )
    finally:
        _reap(emu)
    assert p.returncode == 1, p.stderr
    assert "Traceback" not in p.stderr
    errors = [ln for ln in p.stderr.splitlines() if ln.startswith("robtraj: error:")]
    assert len(errors) == 1 and "disk full" in errors[0]
    summary = load_json(tmp_path / "summary.json")
    assert summary["stop_reason"] == "disk_full"
    out = read_recording(tmp_path / "out.h5")
    assert out.n_frames >= summary["written"]
    src = read_recording(tmp_path / "src.h5")
    k = summary["written"]
    np.testing.assert_array_equal(
        np.float32(out.positions[:k] * 1e3), np.float32(src.positions[:k] * 1e3)
    )


def _one_line_error(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("robtraj: error: ")
    return lines[0]


def test_record_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "out.h5"
    out.write_bytes(b"keep me")
    assert main(["record", "--port", "socket://127.0.0.1:1", "-o", str(out)]) == 2
    assert "exists" in _one_line_error(capsys.readouterr().err)
    assert out.read_bytes() == b"keep me"


def test_bad_port_process_exits_2_with_one_line(tmp_path):
    p = subprocess.run(
        robtraj_cmd("record", "--port", "/dev/no-such-tty", "-o", str(tmp_path / "o.h5")),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert p.returncode == 2
    assert "cannot open port /dev/no-such-tty" in _one_line_error(p.stderr)
    assert not (tmp_path / "o.h5").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["record", "--port", "socket://127.0.0.1:1", "-o", "{tmp}/o.h5"], "cannot open port"),
        (["record", "--port", "bogus://x", "-o", "{tmp}/o.h5"], "cannot open port"),
        (
            ["record", "--port", "loop://", "-o", "{tmp}/o.h5", "--protocol", "x"],
            "unknown protocol",
        ),
        (["record", "--port", "loop://", "-o", "{tmp}/no/o.h5"], "does not exist"),
        (["emulate", "{tmp}/missing.h5", "--port", "pty"], "no such file"),
        (["emulate", "{tmp}/src.h5", "--port", "/dev/ttyS0"], "serves socket://"),
        (["emulate", "{tmp}/src.h5", "--port", "pty", "--faults", "melt=1"], "bad fault"),
    ],
)
def test_bad_input_is_one_line_exit_2(tmp_path, capsys, args, message):
    write_synthetic(tmp_path / "src.h5", n=10)
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    assert main(args) == 2
    assert message in _one_line_error(capsys.readouterr().err)
    assert not (tmp_path / "o.h5").exists()
