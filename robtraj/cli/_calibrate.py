"""`robtraj calibrate`: bundle calibration of a recording → CALIB.json."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from .._errors import UserError
from . import _output
from ._analysis_inputs import warn_undetermined

#: poses listed when the recording leaves a rigid transform undetermined or weak
SUGGESTED_POSES = 6

#: exit status when the solve stopped before its convergence criterion held
NOT_CONVERGED = 3


def register(sub) -> argparse.ArgumentParser:
    from ..model import EFFECT_NAMES

    p = sub.add_parser(
        "calibrate",
        help="calibrate camera, tool mount, LED constellation (and effects) jointly",
        description=(
            "Bundle calibration (Optimistix Levenberg-Marquardt over all frames): "
            "camera<-base, flange<-tool, the LED constellation and optionally physical "
            "effects, with covariances, from a closed-form start. Writes CALIB.json. "
            "Exit status: 0 when the solve converged, 3 when it stopped before its "
            "convergence criterion held (CALIB.json is still written, with "
            '"converged": false and the reason), 2 on bad input.'
        ),
    )
    p.add_argument("recording", metavar="REC.h5", help="recording with robot log and tool")
    p.add_argument("-o", "--out", required=True, metavar="CALIB.json", help="file to write")
    p.add_argument(
        "--robust",
        nargs="?",
        const="huber",
        default=None,
        choices=["huber", "cauchy"],
        help="robust loss (IRLS); bare --robust means huber",
    )
    p.add_argument(
        "--estimate",
        default="",
        metavar="NAME,...",
        help="effects to estimate as well, comma-separated: "
        + ", ".join(EFFECT_NAMES)
        + ", or a dictionary term (e.g. joint2_harmonic1, or joint2_map: joint 2's angle "
        "error map, 256 knots per revolution under a Gaussian smoothness prior)",
    )
    p.add_argument(
        "--init",
        metavar="CALIB.json",
        help="start from this calibration (e.g. a named model from `robtraj discrepancy "
        "--calibration-out`): its transforms, constellation and effects are the start, and "
        "its effects not in --estimate stay at its values",
    )
    p.add_argument(
        "--json",
        nargs="?",
        const="-",
        default=None,
        metavar="PATH",
        help="also print the result as JSON (to PATH, or stdout without PATH)",
    )
    p.add_argument(
        "--max-steps",
        type=int,
        default=50,
        metavar="N",
        help="solver steps per solve before giving up (default 50; exit 3 when reached)",
    )
    p.add_argument(
        "--motion-threshold",
        type=float,
        default=None,
        metavar="RAD_S",
        help="speed [rad/s] below which a joint counts as at rest for the velocity-sign "
        "terms (default 0.001; `robtraj discrepancy` estimates it)",
    )
    p.add_argument("--force", action="store_true", help="overwrite CALIB.json if it exists")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from .._progress import progress_status
    from .._recording_reader import open_recording
    from ..model import EFFECT_NAMES, is_effect, map_words, term

    _output.check([args.out, args.json], force=args.force)
    estimate = tuple(s.strip() for s in args.estimate.split(",") if s.strip())
    bad = [e for e in estimate if not is_effect(e)]
    if bad:
        raise UserError(
            f"unknown effect(s) in --estimate: {', '.join(bad)} "
            f"(known: {', '.join(EFFECT_NAMES)} and the dictionary's terms)"
        )
    if args.max_steps < 1:
        raise UserError(f"--max-steps must be at least 1, not {args.max_steps}")
    from ..estimate.calibration import fit

    # the frames are read from the file block by block: memory independent of its length
    with open_recording(args.recording, truth=False) as rec:
        check_leds_seen(rec, args.recording)
        init = _initial(args, rec)
        with progress_status("calibrating") as say:
            res = fit(
                rec,
                estimate=estimate,
                robust=args.robust,
                init=init,
                max_iter=args.max_steps,
                progress=say,
                suggest=SUGGESTED_POSES,
                motion_threshold=args.motion_threshold,
                per_observation=False,
            )
        joints = np.asarray(rec.robot.joints)
    if init is not None:
        res = _carried_over(res, init, args.init)
    doc = res.to_json()
    text = json.dumps(doc, indent=1)
    out = Path(args.out)
    _output.write_text(out, text)
    _output.write_text(args.json, text)
    s = res.sigma
    t = res.camera_from_base.position
    s_cfb = max(s["camera_from_base.tx"], s["camera_from_base.ty"], s["camera_from_base.tz"])
    lines = [
        f"wrote {out}: {res.n_residuals // 3} LED observations, {res.n_params} parameters, "
        f"residual RMS {res.residual_rms_m * 1e6:.1f} µm, "
        f"{'converged' if res.converged else 'NOT converged'} in {res.iterations} steps",
        f"camera<-base position [{t[0]:.5f}, {t[1]:.5f}, {t[2]:.5f}] m "
        + (
            f"(σ {1e6 * s_cfb:.1f} µm; σ are the largest of Gauss–Newton, cluster-robust "
            f"over {res.n_clusters} clusters and model-error field)"
            if np.isfinite(s_cfb)
            else "(σ: not determined)"
        ),
    ]
    if res.noise_model.get("kind") == "uniform":
        lines.append(f"weights: uniform, {res.noise_model.get('reason', 'no noise model')}")
    if "time_offset" in res.estimated:
        lines.append(
            f"time offset {res.time_offset * 1e3:.4f} ms (σ {s['time_offset'] * 1e3:.4f} ms)"
        )
    for name in res.estimated:
        t = term(name)
        if t is not None and t.knots:
            q = joints[:, t.joint]
            c = np.asarray(res.effects[name], float)
            lines.append(map_words(t.joint + 1, c, (float(q.min()), float(q.max()))))
    for d in res.identifiability.get("dropped", []):
        lines.append(
            f"not identifiable, fixed: {d['parameter']} (with {', '.join(d['confounded_with'])})"
        )
    if res.outlier_frames is not None and res.outlier_frames.size:
        lines.append(f"{res.outlier_frames.size} outlier frames")
    if not res.converged:
        lines.append(f"NOT converged: {res.convergence}")
    lines += _next_pose_lines(res.identifiability.get("next_poses"))
    print("\n".join(lines))
    warn_undetermined(res, str(out), "iso9283, deviation and report results depend")
    return 0 if res.converged else NOT_CONVERGED


def _initial(args: argparse.Namespace, rec):
    """The --init calibration, checked against the recording (robot model; joint angles
    outside its maps' fitted range are warned about), or None."""
    if not args.init:
        return None
    from ..calibration_file import check_robot, load_calibration
    from ._analysis_inputs import warn_outside_maps

    init = load_calibration(args.init)
    check_robot(init, rec, args.init)
    if rec.robot is not None:
        warn_outside_maps(init, rec.robot.joints, args.init)
    return init


def _carried_over(res, init, init_path: str):
    """`res` with what it kept of `init`: the maps' documents (knots, σ, fitted range)
    of the maps it held, and the provenance."""
    import dataclasses

    held = {k: v for k, v in init.maps.items() if k in res.effects and k not in res.estimated}
    return dataclasses.replace(
        res,
        maps={**held, **res.maps},
        provenance={
            "command": "calibrate",
            "init": str(init_path),
            "init_provenance": init.provenance,
        },
    )


def _next_pose_lines(nxt) -> list[str]:
    """The suggested poses, each with the largest σ of the watched translations and
    rotations once it and those above it are added (Gauss–Newton prediction)."""
    if not nxt:
        return []

    def worst(sig: dict, kind: str) -> str:
        vals = [v for k, v in sig.items() if k.rsplit(".", 1)[1][0] == kind]
        if not vals:
            return ""
        if any(v is None for v in vals):
            return "not determined"
        return f"{max(vals) * 1e6:.1f} {'µm' if kind == 't' else 'µrad'}"

    out = [
        f"to determine them, measure next (static, {nxt['dwell_s']:g} s each; joint angles "
        "in °) → largest σ of the translations / rotations once added:"
    ]
    before = nxt["sigma_before"]
    out.append(f"   now: {worst(before, 't') or '–'} / {worst(before, 'r') or '–'}")
    for k, (q, sig) in enumerate(zip(nxt["joints_rad"], nxt["sigma_after"])):
        angles = ", ".join(f"{math.degrees(x):.1f}" for x in q)
        out.append(f"  {k + 1}. [{angles}] → {worst(sig, 't') or '–'} / {worst(sig, 'r') or '–'}")
    return out


def check_leds_seen(rec, name: str) -> None:
    """Refuse a recording in which no frame shows the 3 LEDs a tool pose needs (one pass
    over its frames)."""
    from ..recording import finite_points

    n, most, step = rec.positions.shape[0], 0, 1 << 16
    for a in range(0, n, step):  # a block of frames at a time
        most = max(most, int(finite_points(rec.positions[a : a + step]).sum(1).max(initial=0)))
    if n == 0 or most < 3:
        raise UserError(
            f"{name}: at most {most} LED{'s' * (most != 1)} seen in any frame; a tool pose "
            "(and so the calibration) needs at least 3 LEDs seen at once"
        )
