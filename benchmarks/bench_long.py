"""Whole recordings of any length: each command's peak memory and per-frame time on a
long recording against a short one.

A recording of the `paper` scenario (18 LEDs) is simulated at RATE Hz for SHORT minutes
and for HOURS hours (`robtraj simulate`, itself measured), then `robtraj poses`,
`robtraj calibrate`, `robtraj deviation` and `robtraj report` (under that calibration)
and `robtraj discrepancy` run on each, every command a child process
of its own. Per command and length: wall time, time per frame and peak resident memory
(the child's own ``ru_maxrss``, from `os.wait4`). A watchdog reads each child's
resident memory every 0.2 s and stops it above `KILL_GIB` (the machine's memory is
shared; the figure is then "above `KILL_GIB`"), or after `--max-minutes`.

Targets (asserted; exit 1 when missed): on the long recording every command peaks at
≤ 2 GiB and takes ≤ 1.3× the short recording's time per frame. ``--hours 8`` is the
exhaustive run.

    python benchmarks/bench_long.py [--hours 1] [--short 10] [--rate 1000]
        [--commands simulate poses calibrate deviation report discrepancy] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results" / "long_cpu.json"
TARGET_GIB, TARGET_RATIO = 2.0, 1.3
#: a child above this is stopped: its figure is "more than this"
KILL_GIB = 6.0
COMMANDS = ("simulate", "poses", "calibrate", "deviation", "report", "discrepancy")


def _rss_gib(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return 0.0


def _run(args: list[str], max_s: float) -> dict:
    """Run ``robtraj ARGS`` as a child: exit code, wall time [s], peak RSS [GiB], whether
    the watchdog stopped it (and why)."""
    t0 = time.perf_counter()
    log = tempfile.TemporaryFile("w+")  # not a pipe: a full pipe would stop the child
    proc = subprocess.Popen(
        [sys.executable, "-m", "robtraj", *args, "--quiet"], stdout=log, stderr=log
    )
    stopped: list[str] = []

    def watch():
        while proc.poll() is None:
            if _rss_gib(proc.pid) > KILL_GIB:
                stopped.append(f"resident memory above {KILL_GIB} GiB")
                proc.kill()
            elif time.perf_counter() - t0 > max_s:
                stopped.append(f"running longer than {max_s:.0f} s")
                proc.kill()
            time.sleep(0.2)

    watchdog = threading.Thread(target=watch, daemon=True)
    watchdog.start()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    watchdog.join()
    log.seek(0)
    err = log.read()
    return {
        "exit_code": proc.returncode,
        "wall_s": wall,
        "peak_rss_gib": usage.ru_maxrss / 2**20,
        "stopped": stopped[0] if stopped else None,
        "stderr_tail": err.strip().splitlines()[-1] if err.strip() else "",
    }


def _arguments(command: str, rec: Path, tmp: Path, tag: str, rate: float, seconds: float):
    if command == "simulate":
        return ["simulate", str(rec), "--scenario", "paper", "--duration", f"{seconds:g}",
                "--rate", f"{rate:g}", "--seed", "0"]  # fmt: skip
    if command == "deviation":  # under the recording's own calibration (run before it)
        return [command, str(rec), "--calibration", str(tmp / f"{tag}_calib.json"),
                "--json", str(tmp / f"{tag}_deviation.json")]  # fmt: skip
    if command == "report":
        return [command, str(rec), "--calibration", str(tmp / f"{tag}_calib.json"),
                "--out", str(tmp / f"{tag}_report")]  # fmt: skip
    out = {"poses": "poses.h5", "calibrate": "calib.json", "discrepancy": "discrepancy.json"}
    flag = "--json" if command == "discrepancy" else "-o"
    return [command, str(rec), flag, str(tmp / f"{tag}_{out[command]}")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--short", type=float, default=10.0, help="minutes of the short recording")
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--commands", nargs="+", default=list(COMMANDS), choices=COMMANDS)
    ap.add_argument("--max-minutes", type=float, default=90.0, help="per command")
    ap.add_argument("--json", type=Path, default=RESULTS)
    args = ap.parse_args()

    lengths = {"short": args.short * 60.0, "long": args.hours * 3600.0}
    rows: dict[str, dict[str, dict]] = {}
    with tempfile.TemporaryDirectory(dir=os.environ.get("TMPDIR")) as d:
        tmp = Path(d)
        for tag, seconds in lengths.items():
            rec = tmp / f"{tag}.h5"
            n = int(round(seconds * args.rate))
            for command in ("simulate", *[c for c in args.commands if c != "simulate"]):
                if command != "simulate" and not rec.exists():
                    break
                a = _arguments(command, rec, tmp, tag, args.rate, seconds)
                r = _run(a, args.max_minutes * 60.0)
                r.update(frames=n, us_per_frame=r["wall_s"] / n * 1e6)
                rows.setdefault(command, {})[tag] = r
                print(
                    f"{command:12s} {tag:5s} {n:>9,d} frames: {r['wall_s']:8.1f} s "
                    f"({r['us_per_frame']:6.1f} µs/frame), peak {r['peak_rss_gib']:5.2f} GiB"
                    + (f", STOPPED: {r['stopped']}" if r["stopped"] else "")
                    + (f", exit {r['exit_code']}: {r['stderr_tail']}" if r["exit_code"] else ""),
                    flush=True,
                )

    missed = []
    for command in args.commands:
        long, short = rows.get(command, {}).get("long"), rows.get(command, {}).get("short")
        if long is None or short is None:
            missed.append(f"{command}: not run (its recording was not written)")
            continue
        ratio = long["us_per_frame"] / short["us_per_frame"]
        rows[command]["per_frame_ratio"] = ratio
        if long["stopped"] or long["exit_code"]:
            missed.append(f"{command}: {long['stopped'] or 'exit ' + str(long['exit_code'])}")
        elif long["peak_rss_gib"] > TARGET_GIB:
            missed.append(f"{command}: peak {long['peak_rss_gib']:.2f} GiB > {TARGET_GIB}")
        elif ratio > TARGET_RATIO:
            missed.append(f"{command}: per-frame time {ratio:.2f}× the short one > {TARGET_RATIO}")
    doc = {
        "benchmark": "bench_long",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "rate_hz": args.rate,
        "short_s": lengths["short"],
        "long_s": lengths["long"],
        "targets": {"peak_rss_gib": TARGET_GIB, "per_frame_ratio": TARGET_RATIO},
        "commands": rows,
        "missed": missed,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {args.json}")
    for m in missed:
        print(f"MISSED {m}")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
