"""Shared helpers for the acquisition tests: a synthetic recording and the ledger check."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from robtraj.recording import Recording, read_recording, write_recording

ROOT = Path(__file__).resolve().parents[2]
FRAME_INDEX0 = (1 << 32) - 700  # the u32 counter wraps after 700 frames


def synthetic_recording(
    n: int = 2000, m: int = 18, rate: float = 1000.0, seed: int = 1
) -> Recording:
    """A small device-like recording: random NaN occlusion, low-signal LEDs, temperature."""
    rng = np.random.default_rng(seed)
    t = 0.25 + np.arange(n) / rate
    pos = rng.normal(size=(n, m, 3)) * 0.3 + np.array([0.0, 0.0, 2.0])
    occluded = rng.random((n, m)) < 0.1
    pos[occluded] = np.nan
    status = np.where(occluded, 1, 0).astype(np.uint8)
    status[~occluded & (rng.random((n, m)) < 0.02)] = 3
    temperature = (24.0 + 0.01 * np.arange(n) / rate + 0.05 * rng.standard_normal(n)).astype(
        np.float32
    )
    return Recording(
        time=t,
        frame_index=FRAME_INDEX0 + np.arange(n, dtype=np.uint64),
        led_ids=np.arange(3, 3 + m, dtype=np.int32),
        positions=pos,
        status=status,
        temperature=temperature,
        attrs={"source": "simulation"},
    )


def write_synthetic(path: Path, **kw) -> Recording:
    rec = synthetic_recording(**kw)
    write_recording(rec, path)
    return rec


def expected_resyncs(ledger: dict) -> int:
    """Undecodable stretches the decoder must report, from the emulator's ledger."""
    msgs = ledger["messages"]
    runs, in_run = 0, False
    for fate, noise in zip(msgs["fate"], msgs["noise"]):
        if fate in ("dropped", "lost_disconnected", "unsent"):
            if noise:
                in_run = True
            continue
        if noise or fate in ("corrupted", "truncated"):
            in_run = True
        if fate == "disconnect":  # the cut message is flushed as junk when the link drops
            runs += 1
            in_run = False
        elif fate == "intact" and in_run:
            runs += 1
            in_run = False
    return runs + in_run


def check_against_ledger(src: Recording, out_path: Path, ledger: dict, summary: dict) -> Recording:
    """Every intact frame recorded exactly (float32), none invented, counts as the ledger says."""
    msgs = ledger["messages"]
    kinds, idx, fates = msgs["kind"], msgs["index"], msgs["fate"]
    intact = [i for k, i, f in zip(kinds, idx, fates) if k == "frame" and f == "intact"]
    assert intact, "the emulator sent no intact frame"
    out = read_recording(out_path)
    assert out.n_frames == len(intact), (out.n_frames, len(intact))
    intact = np.asarray(intact)
    # none invented, none missing: the recorded frames are exactly the intact ones
    fi_src = np.asarray(src.frame_index, np.int64)[intact]
    fi_out = np.asarray(out.frame_index, np.int64)
    np.testing.assert_array_equal(fi_out - fi_out[0], fi_src - fi_src[0])
    assert np.all(np.diff(fi_out) > 0)
    np.testing.assert_array_equal(out.led_ids, src.led_ids)
    np.testing.assert_array_equal(out.time, np.round(src.time[intact] * 1e6) / 1e6)
    want = np.float32(src.positions[intact] * 1000.0)
    got = np.float32(out.positions * 1000.0)
    np.testing.assert_array_equal(got, want)  # NaN where NaN, else equal to float32
    np.testing.assert_array_equal(out.status, src.status[intact])
    # temperature: the last status message that arrived intact before each frame
    expect_temp = {}
    current = np.nan
    for k, i, f in zip(kinds, idx, fates):
        if k == "status" and f == "intact":
            current = float(src.temperature[i])
        elif k == "frame" and f == "intact":
            expect_temp[i] = current
    np.testing.assert_array_equal(out.temperature, np.float32([expect_temp[i] for i in intact]))
    # counts
    span = fi_src[-1] - fi_src[0] + 1
    assert summary["lost"] == span - len(intact)
    assert summary["frames"] == summary["written"] == len(intact)
    assert summary["out_of_order"] == 0
    dec = summary["decoder"]
    assert dec["resyncs"] == expected_resyncs(ledger)
    damaged = sum(f in ("corrupted", "truncated", "disconnect") for f in fates)
    detected = sum(dec[k] for k in ("bad_header_crc", "bad_body_crc", "bad_length", "truncated"))
    assert detected >= (damaged > 0)
    assert dec["unknown_type"] == 0
    n_status = sum(k == "status" and f == "intact" for k, f in zip(kinds, fates))
    assert dec["status_messages"] == n_status
    return out


def robtraj_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "robtraj", *args]


def popen(*args: str, **kw) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        robtraj_cmd(*args),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=ROOT,
        **kw,
    )


def wait_for_file(path: Path, timeout: float = 30.0, proc: subprocess.Popen | None = None) -> str:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if path.exists():
            return path.read_text().strip()
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"process ended early: {proc.communicate()}")
        time.sleep(0.02)
    raise AssertionError(f"{path} did not appear within {timeout} s")


def load_json(path: Path) -> dict:
    return json.loads(Path(path).read_text())
