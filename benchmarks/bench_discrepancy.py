"""Discrepancy workflow on a 60 s, 1 kHz recording with a hidden effect (issue 7).

Reports the wall time of `discover` (JIT compile included, as a user meets it on a first
run) and of a second run on a recording of the same shape (compiled functions reused).
Target: under 2 minutes on a 2-core machine.

Then the first round of the search both ways, in the same process: Rao's score test of
every candidate (`score_effects`, what `discover` does) against refitting the nominal
model with each candidate added (the likelihood-ratio way; each effect set is a new
compilation), with the two statistics side by side.

    python benchmarks/bench_discrepancy.py [--duration 60] [--rate 1000]
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import numpy as np

import robtraj  # noqa: F401
from robtraj.analysis.discrepancy import discover
from robtraj.estimate import observation_noise
from robtraj.estimate.calibration import fit, score_effects
from robtraj.model import EFFECT_NAMES
from robtraj.sim import simulate


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--json", metavar="PATH")
    a = ap.parse_args()
    hidden = {"joint_compliance": 1.5e-6}
    times = []
    for seed in (0, 1):
        rec = simulate("calibration", seed=seed, duration=a.duration, rate=a.rate, effects=hidden)
        rec = rec.replace(truth=None)
        t0 = time.perf_counter()
        res = discover(rec)
        times.append(time.perf_counter() - t0)
        print(
            f"seed {seed}: {rec.n_frames} frames, discover {times[-1]:.1f} s, named {res.named}, "
            f"gap {res.gap_before_m * 1e6:.1f} → {res.gap_after_m * 1e6:.1f} µm"
        )
    # first round both ways on the last recording
    _, var = observation_noise(rec)
    w = np.where(rec.visible & np.isfinite(var), 1.0 / var, 0.0)
    nominal = fit(rec, weights=w)
    t0 = time.perf_counter()
    scores = score_effects(rec, nominal, EFFECT_NAMES, weights=w)
    t_score = time.perf_counter() - t0
    t0 = time.perf_counter()
    lr = {}
    for e in EFFECT_NAMES:
        lr[e] = nominal.chi2 - fit(rec, estimate=(e,), weights=w, init=nominal).chi2
    t_refit = time.perf_counter() - t0
    print(f"round 1: score test {t_score:.1f} s, refit per candidate {t_refit:.1f} s")
    for e in EFFECT_NAMES:
        print(f"  {e:18s} score {scores[e]['statistic']:14.1f}  LR {lr[e]:14.1f}")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out = {
        "frames": rec.n_frames,
        "first_run_s": round(times[0], 1),
        "second_run_s": round(times[1], 1),
        "round1_score_test_s": round(t_score, 1),
        "round1_refit_each_s": round(t_refit, 1),
        "round1_speedup": round(t_refit / t_score, 1),
        "statistics": {e: [scores[e]["statistic"], lr[e]] for e in EFFECT_NAMES},
        "peak_rss_mib": round(peak),
    }
    print(json.dumps(out))
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
