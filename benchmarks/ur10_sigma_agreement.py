"""Real UR10 data: do Series A and Series B agree within their quoted σ?

The same robot measured twice: each effect parameter estimated on A and on B should agree
within 2 combined σ for about 95 % of the parameters when the σ are honest; the issue's
target is ≥ 90 % (`TARGET`), asserted here for every model on the real series. For three
models fitted on all poses of each series (the kinematic calibration without and with the
link twists, and the model the workflow names), the share of shared effect parameters
(maps excluded: their knots are not shared where the series' joint ranges differ) whose
A–B difference lies within 2 combined σ: the quoted σ (`PoseFit.sigma`: the largest of
Gauss–Newton, the region jackknife and the covariance under the model-error field) and
the Gauss–Newton σ alone; with the parameters outside the quoted σ listed, the median
|z| and each fit's model-error field (its variance ratios per correlation length).

The same on a twin with known truth: both series' real poses (joint angles, tracker←base
and flange←probe as fitted) measured on one simulated robot, A's named model, with the
tracker noise Series B reports (RMS of its standard deviations, position and rotation):
the A–B differences then come only from the designs, the noise and the model error of
the smaller models (the maps and compliance they leave out). There, each fit's
parameters are also compared with the truth's.

    python benchmarks/ur10_sigma_agreement.py [--data PATH] [--json PATH]

Results: `benchmarks/results/ur10_sigma_agreement.json`. Not a timing; exits non-zero
when a model's real agreement is below `TARGET`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from robtraj.analysis import real_data as rd

#: share of the shared parameters within 2 combined quoted σ (the issue's target)
TARGET = 0.9
NAMED = "named (maps, twists, lengths, compliance[1,2], offsets)"
MODELS = {
    "offsets + lengths": ("link_length", "joint_offset"),
    "offsets + lengths + twists": ("link_length", "joint_offset", "link_twist"),
    NAMED: (
        "joint_map",
        "link_twist",
        "link_length",
        "joint_compliance[1,2]",
        "joint_offset",
    ),
}


def _shared(pa: dict, pb: dict) -> list[str]:
    return sorted(n for n in set(pa) & set(pb) if "map" not in n)


def _share(diff: np.ndarray, sigma: np.ndarray) -> float:
    return float(np.mean(np.abs(diff) <= 2 * sigma))


def agreement(a: rd.PoseFit, b: rd.PoseFit) -> dict:
    """Share of the shared non-map parameters within 2 combined σ, quoted and
    Gauss–Newton, and the median |z| with the quoted σ."""
    pa, pb = a.parameters(), b.parameters()
    shared = _shared(pa, pb)
    idx = [rd.parameter_names(maps=a.has_maps).index(n) for n in shared]
    diff = np.array([pa[n][0] - pb[n][0] for n in shared])
    quoted = np.hypot(np.asarray(a.sigma)[idx], np.asarray(b.sigma)[idx])
    classic = np.hypot(a.sigma_model[idx], b.sigma_model[idx])
    z = np.abs(diff) / quoted
    return {
        "parameters": len(shared),
        "within_2_robust_sigma": _share(diff, quoted),
        "within_2_classic_sigma": _share(diff, classic),
        "median_abs_z": float(np.median(z)),
        "outside_robust": {n: float(v) for n, v in zip(shared, z) if v > 2},
        "model_error_field": {f.series: f.robust_terms["model_error"] for f in (a, b)},
    }


def against_truth(f: rd.PoseFit, truth: rd.PoseFit) -> dict:
    """Share of `f`'s effect parameters within 2 of its σ of the truth's value."""
    pf_, pt = f.parameters(), truth.parameters()
    shared = _shared(pf_, pt)
    diff = np.array([pf_[n][0] - pt[n][0] for n in shared])
    return {
        "within_2_robust_sigma": _share(diff, np.array([pf_[n][1] for n in shared])),
        "within_2_classic_sigma": _share(
            diff,
            np.array([f.sigma_model[rd.parameter_names(maps=f.has_maps).index(n)] for n in shared]),
        ),
    }


def twin(series: dict, truth: rd.PoseFit, noise: np.ndarray, seed: int = 0) -> dict:
    """Both series' real poses measured on one simulated robot: `truth`'s effects (each
    series' own rigid transforms refitted to it), Gaussian tracker noise of σ `noise`
    `(6,)` (position [m], rotation [rad] per axis)."""
    rng = np.random.default_rng(seed)
    out = {}
    for k, s in series.items():
        gen = truth if s.name == truth.series else rd.cross_predict(truth, s)
        noise_k = rng.normal(0.0, noise, (s.n, 6))
        pose = jax.vmap(lambda p, d: (jaxlie.SE3(p) @ jaxlie.SE3.exp(d)).wxyz_xyz)(
            jnp.asarray(gen.predict(s)), jnp.asarray(noise_k)
        )
        out[k] = rd.PoseSeries(k, s.joints, np.asarray(pose), None, None)
    return out


def _line(label: str, r: dict) -> str:
    return (
        f"{label}: {r['parameters']} parameters within 2 σ: quoted "
        f"{100 * r['within_2_robust_sigma']:.0f} %, Gauss–Newton "
        f"{100 * r['within_2_classic_sigma']:.0f} %; median |z| {r['median_abs_z']:.2f}; "
        "outside: " + ", ".join(f"{n} {z:.1f}σ" for n, z in r["outside_robust"].items())
    )


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
    truth = rd.fit_poses(series["A"], estimate=MODELS[NAMED])
    std = np.nan_to_num(np.asarray(series["B"].std, float))
    noise = np.repeat([np.sqrt(np.mean(std[:, :3] ** 2)), np.sqrt(np.mean(std[:, 3:] ** 2))], 3)
    print(f"twin's tracker noise: {noise[0] * 1e6:.1f} µm, {np.rad2deg(noise[3]):.4f}° per axis")
    twin_label = "twin (truth: A's named model)"
    out = {"real": {}, twin_label: {}}
    for kind, data in (("real", series), (twin_label, twin(series, truth, noise))):
        print(kind)
        for label, estimate in MODELS.items():
            fa, fb = (rd.fit_poses(data[k], estimate=estimate) for k in ("A", "B"))
            out[kind][label] = r = agreement(fa, fb)
            print("  " + _line(label, r))
            if kind == twin_label:
                r["against_truth"] = {f.series: against_truth(f, truth) for f in (fa, fb)}
                print(
                    "    against the truth, within 2 σ (quoted, Gauss–Newton): "
                    + "; ".join(
                        f"{k} {100 * v['within_2_robust_sigma']:.0f} %, "
                        f"{100 * v['within_2_classic_sigma']:.0f} %"
                        for k, v in r["against_truth"].items()
                    )
                )
    missed = [k for k, r in out["real"].items() if r["within_2_robust_sigma"] < TARGET]
    out["target"] = {"within_2_robust_sigma": TARGET, "missed": missed}
    with open(a.json, "w") as fh:
        json.dump(out, fh, indent=1)
    if missed:
        raise SystemExit(f"real A–B agreement below {100 * TARGET:.0f} % for: {', '.join(missed)}")


if __name__ == "__main__":
    main()
