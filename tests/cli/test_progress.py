"""Progress of a command that passes over a recording, on a real terminal (a pty): the
frames done of the total, their rate and the time left; nothing with ``--quiet``, and
nothing when stderr is not a terminal (a log file stays clean)."""

import os
import pty
import re
import subprocess
import sys

import pytest

from robtraj import write_recording
from robtraj.sim import simulate


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("progress") / "rec.h5"
    # long enough for the bar to be drawn (rich refreshes 10 times a second)
    write_recording(simulate("paper", seed=0, duration=120.0, rate=1000.0), path)
    return path


def _on_a_terminal(*args: str) -> tuple[int, str]:
    """Exit code and everything `robtraj ARGS` wrote to its terminal (stdout and stderr)."""
    leader, follower = pty.openpty()
    proc = subprocess.Popen(
        [sys.executable, "-m", "robtraj", *args],
        stdin=subprocess.DEVNULL,
        stdout=follower,
        stderr=follower,
        env={**os.environ, "COLUMNS": "160", "TERM": "xterm"},
    )
    os.close(follower)
    chunks = []
    while True:
        try:
            data = os.read(leader, 65536)
        except OSError:  # the follower side closed: the command ended
            break
        if not data:
            break
        chunks.append(data)
    os.close(leader)
    return proc.wait(), b"".join(chunks).decode(errors="replace")


def test_poses_shows_frames_rate_and_time_left_on_a_terminal(recording, tmp_path):
    code, out = _on_a_terminal("poses", str(recording), "-o", str(tmp_path / "p.h5"))
    assert code == 0, out
    # each redraw (erase line) on a line of its own, colours removed
    text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", out.replace("\x1b[2K", "\n"))
    bars = re.findall(r"poses\s.*?(\d+)/120000 frames\s*([\d,]*)(?: frames/s)? left (\S+)", text)
    assert bars, out[-2000:]
    done = [int(d) for d, _, _ in bars]
    assert done[-1] == 120_000 and all(0 <= d <= 120_000 for d in done)
    assert any(rate.replace(",", "").isdigit() and rate != "0" for _, rate, _ in bars)
    assert all(re.fullmatch(r"\d+:\d\d:\d\d|-:--:--", left) for _, _, left in bars)


def test_quiet_draws_nothing(recording, tmp_path):
    code, out = _on_a_terminal("poses", str(recording), "-o", str(tmp_path / "q.h5"), "--quiet")
    assert code == 0, out
    assert "frames/s" not in out and "left" not in out
    assert "wrote" in out  # the result is still reported


def test_no_progress_into_a_file(recording, tmp_path):
    run = subprocess.run(
        [sys.executable, "-m", "robtraj", "poses", str(recording), "-o", str(tmp_path / "f.h5")],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    assert "frames/s" not in run.stderr and "\x1b[" not in run.stderr
