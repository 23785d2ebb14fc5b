"""How long `robtraj simulate` takes for a 60 s, 1 kHz, 18-LED recording, and its peak memory.

Runs the real command in a fresh process (JIT compile included, as a user meets it) and
reads the child's peak resident memory. Target (issue 2): under 30 s on a 2-core machine.

    python benchmarks/bench_simulate.py [--duration 60] [--rate 1000] [--scenario paper]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--json", metavar="PATH")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "bench.h5"
        cmd = [
            sys.executable,
            "-m",
            "robtraj",
            "simulate",
            str(out),
            "--scenario",
            a.scenario,
            "--duration",
            str(a.duration),
            "--rate",
            str(a.rate),
        ]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        size = out.stat().st_size
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024  # kB → MiB (Linux)
    frames = int(a.duration * a.rate)
    res = {
        "scenario": a.scenario,
        "frames": frames,
        "leds": 18,
        "wall_s": round(wall, 2),
        "peak_rss_mib": round(peak, 1),
        "file_mib": round(size / 2**20, 1),
        "target_s": 30,
    }
    print(
        f"robtraj simulate {a.scenario}: {frames} frames × 18 LEDs in {wall:.1f} s "
        f"(process start and JIT included), peak RSS {peak:.0f} MiB, file {size / 2**20:.1f} MiB"
    )
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
