"""Real UR10 data (shared/data/ipa-robot-accuracy): the full-data figures of
docs/real_ur10.md, and the wall time of the workflow on all poses.

Runs the pose-level discrepancy workflow with cross-series validation on every pose of
Series A (11 911) and Series B (1 495), then the extras the document quotes: the
cross-series prediction with only camera←base refitted, the flange←probe of the two
series compared, and the calibration of Series B with pure 1/std² weights.

    python benchmarks/bench_real_ur10.py [--every-a 1] [--every-b 1] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

import robtraj  # noqa: F401
from robtraj.analysis import real_data as rd


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--every-a", type=int, default=1)
    ap.add_argument("--every-b", type=int, default=1)
    ap.add_argument("--json", metavar="PATH")
    ap.add_argument(
        "--data",
        default=str(Path(__file__).resolve().parents[2] / "shared" / "data" / "ipa-robot-accuracy"),
        help="the ipa-robot-accuracy data set folder (default: ../shared/data/...)",
    )
    a = ap.parse_args()
    t0 = time.perf_counter()
    series = {
        "A": rd.load_series("A", a.data).every(a.every_a),
        "B": rd.load_series("B", a.data).every(a.every_b),
    }
    wf = rd.run_workflow(
        series, progress=lambda m: print(f"{time.perf_counter() - t0:7.1f} s  {m}", flush=True)
    )
    wall = time.perf_counter() - t0
    print(f"\nposes: A {series['A'].n}, B {series['B'].n}; workflow {wall:.1f} s")
    print("named:", wf.named)
    print()
    print(wf.markdown())
    print("candidates (round, effect, ΔBIC per fitted series, cross-series gain):")
    for e in wf.candidates_tried:
        bic = {k: round(v["delta_bic"]) for k, v in e["score"].items()}
        gain = {k: round(v, 3) for k, v in e["cross_gain"].items()}
        print(f"  {e['round']} {e['effect']:17s} ΔBIC {bic}  cross gain {gain}")
    extra: dict = {}
    models = {"nominal rigid": wf.models[0], "calibration": wf.calibration}
    models.update({f"+ {e}": m for e, m in zip(wf.named, wf.models[1:])})
    print("\ncross-series with only camera←base refitted (flange←probe from the fitting series):")
    rows = []
    for label, m in models.items():
        for key, v in rd.rigid_variants(m, series).items():
            s = v["camera"].summary(wf.noise_m[key[-1]])
            rows.append({"model": label, "column": f"{key} (camera only)", **s})
    print(rd.rows_markdown(rows))
    extra["camera_only"] = rows
    fa, fb = wf.models[0].fitted["A"], wf.models[0].fitted["B"]
    dt, da = rd.transform_difference(fa.flange_from_probe, fb.flange_from_probe)
    dtc, dac = rd.transform_difference(fa.camera_from_base, fb.camera_from_base)
    ca, cb = wf.calibration.fitted["A"], wf.calibration.fitted["B"]
    dtk, dak = rd.transform_difference(ca.flange_from_probe, cb.flange_from_probe)
    print(
        f"flange←probe A vs B: nominal {dt * 1e3:.3f} mm / {np.rad2deg(da):.4f} deg, "
        f"calibrated {dtk * 1e3:.3f} mm / {np.rad2deg(dak):.4f} deg; "
        f"camera←base A vs B: {dtc * 1e3:.1f} mm / {np.rad2deg(dac):.3f} deg"
    )
    extra["flange_from_probe_A_vs_B"] = {"nominal": [dt, da], "calibrated": [dtk, dak]}
    extra["camera_from_base_A_vs_B"] = [dtc, dac]
    # Series B with pure 1/std² weights (no unexplained-variance term)
    pure = rd.fit_poses(series["B"], estimate=rd.CALIBRATION, block_sigma=(1e-12, 1e-12))
    cross = rd.fit_poses(
        series["A"], fixed=pure, block_sigma=wf.calibration.fitted["A"].block_sigma
    )
    print(
        "calibration on B with pure 1/std² weights:",
        "fit B",
        {k: round(v, 4) for k, v in pure.summary().items()},
        "B->A",
        {k: round(v, 4) for k, v in cross.summary().items()},
    )
    extra["pure_std_weights"] = {"fit B": pure.summary(), "B->A": cross.summary()}
    for label, m in models.items():
        for k, f in m.fitted.items():
            if f.identifiability["dropped"]:
                print(label, k, "fixed:", [d["parameter"] for d in f.identifiability["dropped"]])
    print("\ncalibration parameters (value ± σ):")
    for k, f in wf.calibration.fitted.items():
        for name, (v, s) in f.parameters().items():
            unit = "mrad" if "offset" in name else "mm"
            print(f"  {k} {name:22s} {v * 1e3:+.3f} ± {s * 1e3:.3f} {unit}")
    total = time.perf_counter() - t0
    print(f"total {total:.1f} s")
    if a.json:
        doc = wf.to_json()
        out = {
            "poses": {k: s.n for k, s in series.items()},
            "wall_s": wall,
            "total_s": total,
            "cpu_count": os.cpu_count(),
            **{k: doc[k] for k in ("named", "rejected", "calibration_parameters")},
            **{k: doc[k] for k in ("fixed_unidentifiable", "table", "candidates")},
            **extra,
        }
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
