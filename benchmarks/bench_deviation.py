"""Path deviation of 6·10⁵ measured points against 1.2·10⁶ reference samples.

A rectangle (0.6 m × 0.4 m) with a 90° reorientation along each side is repeated 150
times, each cycle 1 mm above the last: the commanded path is 300 m long, sampled every 0.25 mm (1.2·10⁶ samples); the
measured path is the same motion at 1 kHz and 0.5 m/s (6·10⁵ frames, 0.5 mm apart)
with a smooth vertical deviation of up to 0.6 mm and 50 µm noise, so the nearest
sample often lies on the neighbouring pass 1 mm away: the hard case for the matching. Reports the wall time of `path_deviation` (monotone, the default), the
unconstrained variant, and a plain `scipy.spatial.cKDTree` nearest-sample baseline
(build + query, the floor for any k-d-tree method) in the same run, and the peak
resident memory of the process.

    python benchmarks/bench_deviation.py [--frames 600000] [--samples 1200000] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

import robtraj  # noqa: F401  (x64)
from robtraj.analysis import commanded_path, path_deviation
from robtraj.recording import Pose, Program


def _program(cycles: int) -> Program:
    corners = np.array([[0.0, 0.0, 0.0], [0.6, 0.0, 0.0], [0.6, 0.4, 0.0], [0.0, 0.4, 0.0]])
    angles = np.radians([0.0, 90.0, 0.0, -90.0])
    lift = np.repeat(np.arange(cycles + 1) * 1e-3, 4)[: 4 * cycles + 1, None] * [0.0, 0.0, 1.0]
    pos = np.concatenate([np.tile(corners, (cycles, 1)), corners[:1]]) + [1.0, 0.0, 0.9] + lift
    ang = np.concatenate([np.tile(angles, cycles), angles[:1]])
    quat = Rotation.from_euler("z", ang[:, None]).as_quat()[:, [3, 0, 1, 2]]
    motion = np.array(["start"] + ["linear"] * (len(pos) - 1))
    return Program(Pose(pos, quat), motion, np.full(len(pos), 0.5))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=600_000)
    ap.add_argument("--samples", type=int, default=1_200_000)
    ap.add_argument("--json", metavar="PATH")
    a = ap.parse_args()
    cycles = 150
    length = cycles * 2.0
    prog = _program(cycles)
    ref = commanded_path(prog, length / a.samples)
    rng = np.random.default_rng(0)
    s = np.linspace(0.0, ref.progress[-1], a.frames)
    pos = np.column_stack([np.interp(s, ref.progress, ref.position[:, i]) for i in range(3)])
    pos[:, 2] += 6e-4 * np.sin(s / 0.3)
    pos += rng.normal(0.0, 5e-5, pos.shape)
    idx = np.clip(np.searchsorted(ref.progress, s), 0, ref.n_samples - 1)
    quat = ref.quaternion_wxyz[idx]

    path_deviation(ref, pos[:2000], quat[:2000])  # JIT compile of the matching programme
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    t0 = time.perf_counter()
    tree = cKDTree(ref.position)
    _, nearest = tree.query(pos, k=1, workers=-1)
    t_base = time.perf_counter() - t0

    t0 = time.perf_counter()
    free = path_deviation(ref, pos, quat, monotone=False)
    t_free = time.perf_counter() - t0

    t0 = time.perf_counter()
    res = path_deviation(ref, pos, quat)
    t_mono = time.perf_counter() - t0
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    err_mono = np.abs(res.progress - s)
    err_free = np.abs(free.progress - s)
    out = {
        "frames": a.frames,
        "reference_samples": ref.n_samples,
        "kdtree_baseline_s": round(t_base, 3),
        "deviation_unconstrained_s": round(t_free, 3),
        "deviation_monotone_s": round(t_mono, 3),
        "peak_rss_mib_before": round(rss0, 1),
        "peak_rss_mib": round(rss1, 1),
        "monotone_progress_error_max_mm": round(float(err_mono.max()) * 1e3, 4),
        "unconstrained_frames_on_wrong_pass": int(np.sum(err_free > 0.01)),
        "monotone_frames_on_wrong_pass": int(np.sum(err_mono > 0.01)),
        "distance_rms_mm": round(res.summary().distance_rms * 1e3, 4),
    }
    print(json.dumps(out, indent=2))
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
