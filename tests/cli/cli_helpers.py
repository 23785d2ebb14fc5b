"""Shared by the CLI tests: run a command in-process and check the one-line error rule."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from robtraj.cli import main
from robtraj.recording import Recording, write_recording


def run_cli(capsys, *args: str) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of `robtraj ARGS` run in this process; an exception other
    than SystemExit propagates (a traceback is a failure)."""
    capsys.readouterr()
    try:
        code = main([str(a) for a in args])
    except SystemExit as e:  # argparse
        code = e.code if isinstance(e.code, int) else 2
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code: int, err: str, *needles: str) -> str:
    """Exit 2 and exactly one stderr line ``robtraj: error: …`` containing `needles`."""
    lines = err.strip().splitlines()
    assert code == 2, (code, err)
    assert len(lines) == 1 and lines[0].startswith("robtraj: error: "), err
    assert "Traceback" not in err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def digest(path: Path) -> str | None:
    """SHA-256 of a file, of a folder's files (names and contents), None if absent."""
    path = Path(path)
    if not path.exists():
        return None
    h = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for f in files:
        h.update(str(f.relative_to(path) if path.is_dir() else f.name).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def small_recording(n: int = 50, m: int = 4) -> Recording:
    """A valid schema-1 recording of `n` frames and `m` LEDs (no robot, no program)."""
    rng = np.random.default_rng(0)
    return Recording(
        time=np.arange(n) / 100.0,
        frame_index=np.arange(n, dtype=np.uint64),
        led_ids=np.arange(m, dtype=np.int32),
        positions=rng.normal(size=(n, m, 3)) * 0.05 + np.array([0.0, 0.0, 2.0]),
        attrs={"source": "simulation"},
    )


def write_small(path: Path, **kw) -> Path:
    write_recording(small_recording(**kw), path)
    return path


def valid_calibration(m: int = 4) -> dict:
    """A CALIB.json document the loader accepts (covariance null: from another source)."""
    rng = np.random.default_rng(1)
    return {
        "camera_from_base": {"position": [0.1, 1.0, 3.0], "quaternion_wxyz": [1.0, 0, 0, 0]},
        "flange_from_tool": {"position": [0.0, 0.0, 0.1], "quaternion_wxyz": [0, 1.0, 0, 0]},
        "constellation": {
            "led_ids": list(range(m)),
            "positions": (rng.normal(size=(m, 3)) * 0.05).tolist(),
        },
        "time_offset": 0.0,
        "covariance": None,
        "residual_rms_m": 5e-5,
    }


def true_calibration(rec: Recording) -> dict:
    """The CALIB.json document of a simulated recording's truth (covariance null: from
    another source; the residual RMS a calibration of such a setup reports)."""

    def pose(p):
        return {"position": p.position.tolist(), "quaternion_wxyz": p.quaternion_wxyz.tolist()}

    tr = rec.truth
    return {
        "camera_from_base": pose(tr.camera_from_base),
        "flange_from_tool": pose(tr.flange_from_tool),
        "constellation": {
            "led_ids": np.asarray(rec.tool.led_ids).tolist(),
            "positions": np.asarray(tr.constellation).tolist(),
        },
        "time_offset": 0.0,
        "covariance": None,
        "residual_rms_m": 40e-6,
    }
