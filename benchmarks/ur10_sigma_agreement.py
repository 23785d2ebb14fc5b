"""Real UR10 data: do Series A and Series B agree within their quoted σ?

The same robot measured twice: each effect parameter estimated on A and on B should agree
within 2 combined σ for about 95 % of the parameters when the σ are honest. For three
models fitted on all poses of each series (the kinematic calibration without and with the
link twists, and the model the workflow names), the share of shared effect parameters
(maps excluded: their knots are not shared where the series' joint ranges differ) whose
A–B difference lies within 2 combined robust σ (region jackknife) and within 2 combined
Gauss–Newton σ, with the parameters outside listed.

    python benchmarks/ur10_sigma_agreement.py [--data PATH] [--json PATH]

Results: `benchmarks/results/ur10_sigma_agreement.json`. Not a timing; it asserts nothing
(the figure it reports is an open question for the richer models, see docs/real_ur10.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from robtraj.analysis import real_data as rd

MODELS = {
    "offsets + lengths": ("link_length", "joint_offset"),
    "offsets + lengths + twists": ("link_length", "joint_offset", "link_twist"),
    "named (maps, twists, lengths, compliance[1,2], offsets)": (
        "joint_map",
        "link_twist",
        "link_length",
        "joint_compliance[1,2]",
        "joint_offset",
    ),
}


def agreement(a: rd.PoseFit, b: rd.PoseFit) -> dict:
    """Share of the shared non-map parameters within 2 combined σ, robust and classic."""
    pa, pb = a.parameters(), b.parameters()
    shared = sorted(n for n in set(pa) & set(pb) if "map" not in n)
    names = rd.parameter_names(maps=a.has_maps)
    idx = [names.index(n) for n in shared]
    diff = np.array([pa[n][0] - pb[n][0] for n in shared])
    z_robust = np.abs(diff) / np.hypot(np.asarray(a.sigma)[idx], np.asarray(b.sigma)[idx])
    z_classic = np.abs(diff) / np.hypot(a.sigma_model[idx], b.sigma_model[idx])
    return {
        "parameters": len(shared),
        "within_2_robust_sigma": float(np.mean(z_robust <= 2)),
        "within_2_classic_sigma": float(np.mean(z_classic <= 2)),
        "outside_robust": {n: float(z) for n, z in zip(shared, z_robust) if z > 2},
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument(
        "--data",
        default=str(Path(__file__).resolve().parents[2] / "shared" / "data" / "ipa-robot-accuracy"),
    )
    ap.add_argument(
        "--json",
        default=str(Path(__file__).resolve().parent / "results" / "ur10_sigma_agreement.json"),
    )
    a = ap.parse_args()
    series = {k: rd.load_series(k, a.data) for k in ("A", "B")}
    out = {}
    for label, estimate in MODELS.items():
        fa, fb = (rd.fit_poses(series[k], estimate=estimate) for k in ("A", "B"))
        out[label] = r = agreement(fa, fb)
        print(
            f"{label}: {r['parameters']} parameters, within 2 robust σ "
            f"{100 * r['within_2_robust_sigma']:.0f} %, within 2 classic σ "
            f"{100 * r['within_2_classic_sigma']:.0f} %; outside: "
            + ", ".join(f"{n} {z:.1f}σ" for n, z in r["outside_robust"].items())
        )
    with open(a.json, "w") as fh:
        json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
