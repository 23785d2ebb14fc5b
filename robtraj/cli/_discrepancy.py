"""`robtraj discrepancy`: name the physical effects the nominal model is missing."""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

from . import _output

#: exit status when the solve stopped before its convergence criterion held
NOT_CONVERGED = 3


def register(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "discrepancy",
        help="find where model and measurement disagree and name the missing effect",
        description=(
            "Fit the nominal model, localise the disagreement, score each effect of the "
            "library (time_offset, joint_offset, link_length, joint_compliance, backlash, "
            "led_angle_bias, tracker_scale, thermal_drift) and each term of the dictionary "
            "(joint-angle harmonics, velocity-sign and torque² joint errors, LED biases along "
            "the emission axis and the line of sight, a scale per camera axis) by a score "
            "test, refit with the best and name it when the likelihood-ratio test, BIC and "
            "held-out time blocks confirm it; a dictionary term replaces the library effects "
            "that stood in for it; repeat; when structure is left, the joint angle error maps, "
            "then terms built from the recording's signals (a joint's angle error as a "
            "product of functions of one or two joint angles or gravity torques: screened "
            "at once, the strongest tested the same way at a significance divided by the "
            "number screened); report structure that nothing explains and where "
            "it lives: the variables ranked by the fraction of the held-out gap that a smooth "
            "function of each alone removes. A recording of more than --search-frames "
            "frames is searched on evenly spaced frames (one in k, read from the file a "
            "block at a time), and the named model fitted again on all of its frames. "
            "Exit status: 0 when the final calibration converged, 3 when "
            "its solve stopped before its convergence criterion held (result still written), "
            "2 on bad input."
        ),
    )
    p.add_argument(
        "recording", metavar="REC.h5", help="recording with robot log, tool, static dwells"
    )
    p.add_argument(
        "--validate-on",
        metavar="OTHER.h5",
        help="6-DOF pose recordings (robtraj import --format pose-csv): each recording names "
        "effects (the library's geometric and compliance effects, every joint's angle error "
        "map) by blocked cross-validation inside itself, and the other one validates them "
        "(docs/real_ur10.md)",
    )
    p.add_argument(
        "--no-constructed",
        action="store_true",
        help="search the library, the dictionary and the joint angle error maps only: no "
        "terms built from the recording's signals (a joint's angle error as a function of "
        "one or two joint angles or gravity torques)",
    )
    p.add_argument(
        "--search-frames",
        type=int,
        metavar="N",
        help="search on at most N evenly spaced frames (default 100 000, ~1.3 GiB; the "
        "floor of the gap falls as N^-1/4); the named model is fitted on all frames",
    )
    p.add_argument("--json", metavar="OUT", help="write the result (DESIGN section 8)")
    p.add_argument(
        "--calibration-out",
        metavar="NAMED.json",
        help="write the final named model of REC.h5 as a CALIB.json (effects, maps with "
        "their knots and σ, rigid transforms, noise model) that evaluate, iso9283, "
        "deviation, report, compensate and calibrate --init read like any other",
    )
    p.add_argument(
        "--report",
        metavar="DIR",
        help="write figures: the gap step by step, residual structure (with --validate-on: "
        "the named joint angle error maps with their ±1σ band)",
    )
    p.add_argument(
        "--force", action="store_true", help="overwrite OUT and the figures in DIR if they exist"
    )
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from .._errors import UserError
    from .._progress import progress_status
    from .._recording_reader import open_recording
    from ..analysis import named_calibration, refit_on_all_frames, search_recording
    from ..analysis.discrepancy import INDISTINCT_BIC, discover
    from ._calibrate import check_leds_seen

    _output.check([args.json, args.calibration_out], [args.report], force=args.force)
    if args.validate_on:
        return _cross_series(args)
    if args.search_frames is not None and args.search_frames < 1:
        raise UserError(f"--search-frames must be at least 1, got {args.search_frames}")
    # the LED positions stay on disk: a long recording is searched on a subset of its
    # frames, and the named model fitted on all of them chunk by chunk
    with open_recording(args.recording, truth=False) as full, progress_status("discrepancy") as say:
        check_leds_seen(full, args.recording)
        rec, every = search_recording(full, args.search_frames)
        res = discover(rec, progress=say, construct=not args.no_constructed)
        if every > 1:
            say("the named model on every frame")
            res = dataclasses.replace(res, calibration=refit_on_all_frames(full, res.calibration))
        n_frames = full.n_frames
    doc = res.to_json()
    doc["search_frames"] = {"every": every, "frames": rec.n_frames, "of": n_frames}
    if every > 1:
        print(
            f"searched on one frame in {every} ({rec.n_frames} of {n_frames}, evenly "
            "spaced); the final model fitted on all frames"
        )
    print(
        f"gap before: {doc['gap_before_m'] * 1e6:.1f} µm (noise σ {doc['noise_sigma_m'] * 1e6:.1f} µm per axis)"
    )
    if doc["localisation_before"] is not None:
        print(f"  {doc['localisation_before']['words']}")
    for s in doc["steps"]:
        params = ", ".join(
            f"{k} = {v['value']:.4g} ± {v['sigma']:.2g}" for k, v in s["parameters"].items()
        )
        held = s["score"]
        what = s["term"]["words"] if "term" in s else params
        print(
            f"+ {s['effect']}: gap {s['gap_after_m'] * 1e6:.1f} µm "
            f"(ΔBIC {held['delta_bic']:.0f}; held-out gap {held['heldout_gap_before_m'] * 1e6:.1f}"
            f" → {held['heldout_gap_after_m'] * 1e6:.1f} µm); {what}"
        )
        if "term" in s:
            acts = s["term"]["acts"]
            lo, hi = acts["variable_range"]
            print(
                f"  acts over {s['term']['variable']} from {lo:.2f} to {hi:.2f} "
                f"{acts['unit']}, at least "
                f"half its peak in {100 * acts['share_above_half_peak']:.0f} % of the recording"
            )
        for e in s["equally_supported"]:
            print(
                f"  equally supported: {e['effect']} in its place (on the held-out blocks "
                f"worse by χ² {e['heldout_chi2_worse']:.1f} only, Vuong z {e['heldout_z']:.2f}): "
                "this recording cannot tell them apart"
            )
            _print_separating(e["next_poses"])
        others = [a for a in s["alternatives"]
                  if a not in {e["effect"] for e in s["equally_supported"]}]  # fmt: skip
        if others:
            print(
                f"  not told apart by the score test from: {', '.join(others)} (ΔBIC within "
                f"{INDISTINCT_BIC:.0f}), but worse on the held-out blocks"
            )
        if s["replaces"]:
            print(
                f"  replaces {', '.join(s['replaces'])}: named before, not needed next to it "
                "(they stood in for it)"
            )
    for r in doc["rejected"]:
        print(
            f"  not named: {r['effect']} (significant, but the held-out gap moves only "
            f"{r['heldout_gap_before_m'] * 1e6:.1f} → {r['heldout_gap_after_m'] * 1e6:.1f} µm)"
        )
    if doc["dropped"]:
        print(f"final model: {', '.join(doc['named']) or 'nominal'}")
    print(
        f"gap after: {doc['gap_after_m'] * 1e6:.1f} µm "
        f"(what a complete model leaves by chance: {doc['gap_floor_m'] * 1e6:.1f} µm)"
    )
    if doc["stopped"] == "gap_within_floor":
        print("stopped: the gap is within its floor, nothing more can be told from the noise")
    if doc["unexplained"]:
        where = doc["localisation_after"]
        print(f"unexplained structure remains: {where['words']}")
        _print_ranking(where)
        if doc["steps"]:
            print(
                "the named effects may partly stand in for it: an effect outside the library "
                "and the dictionary is absorbed by them as far as the data cannot tell them "
                "apart (register a term of your own: robtraj.model.register_effect)"
            )
    else:
        print("no structured residual left beyond the noise")
    if not doc["converged"]:
        print(f"calibration NOT converged: {doc['convergence']}")
    _output.write_json(args.json, doc)
    _write_named(args, named_calibration(res, rec, args.recording))
    if args.report:
        with _output.new_folder(args.report) as tmp:
            figs = [Path(args.report) / Path(f).relative_to(tmp) for f in res.figures(tmp)]
        print(f"figures: {', '.join(str(f) for f in figs)}")
    return 0 if doc["converged"] else NOT_CONVERGED


#: variables listed in the ranking of where the gap left lives
RANKED_SHOWN = 6


def _print_ranking(where: dict) -> None:
    """The first `RANKED_SHOWN` variables of a localisation (`Localisation.to_json`)."""
    from ..analysis.discrepancy import label

    print(
        "  fraction of the held-out gap a smooth function of one variable alone removes "
        "(± σ over the held-out time blocks):"
    )
    for row in where["ranking"][:RANKED_SHOWN]:
        f, s = row["fraction"], row["sigma"]
        value = "n/a" if f is None else f"{100 * f:4.0f} ± {100 * (s or 0.0):.0f} %"
        print(f"    {label(row['variable']):<24} {value}")


def _write_named(args: argparse.Namespace, calib) -> None:
    """Write the named model to --calibration-out, saying what it holds."""
    if not args.calibration_out:
        return
    _output.write_json(args.calibration_out, calib.to_json())
    held = ", ".join(calib.provenance.get("named", [])) or "nominal (nothing named)"
    print(f"named model ({held}) written to {args.calibration_out}")


def _cross_series(args: argparse.Namespace) -> int:
    """The pose workflow (`robtraj.analysis.real_data.run_workflow`) on two pose
    recordings: series A is REC.h5, series B the --validate-on recording. Each names its
    effects by cross-validation inside itself; the other validates them."""
    import numpy as np

    from .._errors import UserError
    from .._progress import progress_status
    from ..analysis import real_data as rd
    from ..recording import read_recording
    from ..report import map_figure

    series, recs = {}, {}
    for key, path in (("A", args.recording), ("B", args.validate_on)):
        recs[key] = rec = read_recording(path)
        if rec.probe is None or rec.robot is None:
            raise UserError(
                f"{path}: --validate-on needs 6-DOF pose recordings with a joint log "
                "(robtraj import --format pose-csv); an LED recording is validated on its "
                "own held-out time blocks without it"
            )
        try:
            series[key] = rd.series_from_recording(rec, key)
        except UserError as e:
            raise UserError(f"{path}: {e}") from None
    with progress_status("discrepancy") as say:
        wf = rd.run_workflow(series, progress=say)
    print(
        f"A = {args.recording} ({series['A'].n} poses), B = {args.validate_on} ({series['B'].n} poses)"
    )
    print(
        "each series names effects by blocked cross-validation inside itself (regions of "
        "joint space left out one at a time); the other series validates them"
    )
    steps = wf.steps
    for key in wf.series:
        print(f"named on {key}: {', '.join(wf.named[key]) or 'nothing'}")
        for s in (s for s in steps if s["series"] == key):
            cv0, cv1 = s["cv_before"], s["cv"]
            cross = ", ".join(
                f"{k} {v['pos_mean_mm']:.3f} mm / {v['ang_mean_deg']:.4f}°"
                for k, v in s["cross"].items()
            )
            print(
                f"+ {s['effect']} (round {s['round']}): cross-validation gain "
                f"{100 * s['cv_gain']:+.1f} % (held-out position RMS {cv0['pos_rms_m'] * 1e3:.3f}"
                f" → {cv1['pos_rms_m'] * 1e3:.3f} mm, angle RMS "
                f"{np.rad2deg(cv0['ang_rms_rad']):.4f} → {np.rad2deg(cv1['ang_rms_rad']):.4f}°);"
                f" ΔBIC {s['delta_bic']:.0f}; validation, not used to name: {cross}"
            )
            if "term" in s:
                for line in s["term"]["words"]:
                    print(f"  {line}")
                prior = s["term"].get("prior")
                if prior:
                    print(
                        f"  prior chosen by cross-validation on {key}: σ_f "
                        f"{prior['sigma_f_rad'] * 1e3:g} mrad, ℓ {prior['length_scale_rad']:g} rad"
                    )
        for e in (e for e in wf.rejected if e["series"] == key):
            print(
                f"  not named: {e['effect']} (round {e['round']}: fits {key} better, ΔBIC "
                f"{e['delta_bic']:.0f}, but the cross-validation gain is "
                f"{100 * e['cv_gain']:+.1f} %)"
            )
    print(wf.markdown())
    _output.write_json(args.json, wf.to_json())
    _write_named(args, wf.calibration_of("A", recs["A"], args.recording))
    if args.report:
        with _output.new_folder(args.report) as tmp:
            figs = []
            for s in steps:
                if "term" in s and s["round"] == max(
                    t["round"] for t in steps if t["series"] == s["series"]
                ):
                    name = f"joint_maps_{s['series']}.png"
                    map_figure(
                        Path(tmp) / name,
                        s["term"]["maps"],
                        f"Joint angle error maps named on {s['series']} (±1σ)",
                    )
                    figs.append(Path(args.report) / name)
        print(f"figures: {', '.join(str(f) for f in figs) or 'none (no maps named)'}")
    return 0


def _print_separating(poses: dict | None) -> None:
    """The static poses that would tell two equally supported models apart."""
    if poses is None:
        print("  no pose in reach would show enough LEDs to tell them apart")
        return
    print(
        f"  measure to tell them apart ({poses['dwell_s']:g} s dwell each; the χ² each adds "
        f"against the wrong one, the whole recording: {poses['chi2_recording']:.1f}):"
    )
    for q, c in zip(poses["joints_rad"], poses["chi2_per_dwell"]):
        angles = ", ".join(f"{math.degrees(a):.1f}" for a in q)
        print(f"    joints [{angles}] °: χ² {c:.0f}")
