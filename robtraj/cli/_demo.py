"""`robtraj demo`: the whole pipeline on a simulated robot with a hidden effect."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ._args import seed

#: the physics the demo hides in the simulated robot (the workflow must find it)
HIDDEN = {"joint_compliance": 1.5e-6}  # [rad/(N·m)]: about 0.5 mm of sag at the TCP
RATE = 250.0  # [Hz] tracker rate of the demo recordings (the device does up to 1000)
#: unit of each effect's values (robtraj.model.Effects)
EFFECT_UNITS = {
    "time_offset": "s",
    "joint_offset": "rad",
    "link_length": "m",
    "link_twist": "rad",
    "joint_compliance": "rad/(N·m)",
    "backlash": "rad",
    "led_angle_bias": "m",
    "tracker_scale": "",
    "thermal_drift": "m/K",
}


def register(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "demo",
        help="simulate a robot with a hidden effect and run the whole pipeline on it",
        description=(
            "Simulate a calibration run and an ISO 9283 cube test of an ABB IRB2400 whose "
            "joints sag under gravity (hidden: the recordings carry no hint of it), then: "
            "per-frame poses -> bundle calibration -> discrepancy discovery (names the "
            "missing effect) -> calibration with it -> ISO 9283 -> path deviation -> HTML "
            "report. Finishes in a few minutes on a laptop."
        ),
    )
    p.add_argument("--out", default="robtraj-demo", metavar="DIR", help="output folder")
    p.add_argument("--seed", type=seed, default=0, help="random seed (>= 0)")
    p.add_argument("--force", action="store_true", help="replace the results in DIR")
    p.set_defaults(func=run)
    return p


class _Steps:
    def __init__(self):
        self.t0 = time.perf_counter()
        self.last = self.t0

    def __call__(self, msg: str) -> None:
        now = time.perf_counter()
        print(f"[{now - self.t0:6.1f} s] {msg}", flush=True)
        self.last = now


def effect_lines(calib, name: str, hidden=None) -> list[str]:
    """One line per estimated entry of effect `name`: value ± σ with the unit."""
    unit = EFFECT_UNITS.get(name, "")
    sigma = calib.sigma
    values = np.ravel(np.asarray(calib.effects[name], float))
    keys = [k for k in calib.parameter_names if k == name or k.startswith(f"{name}[")]
    hidden_values = None if hidden is None else np.ravel(np.broadcast_to(hidden, values.shape))
    lines = []
    for i, v in enumerate(values):
        key = keys[i] if len(keys) == values.size else f"{name}[{i}]"
        s = sigma.get(key, 0.0)
        if s == 0.0 and v == 0.0:
            continue  # not estimated (fixed at 0)
        line = f"{key} = {v:.4g} ± {s:.2g} {unit}".rstrip()
        if hidden_values is not None:
            line += f" (hidden: {hidden_values[i]:g})"
        lines.append(line)
    return lines


def attach_campaign(files):
    """The recording `robtraj attach` makes of a campaign's `files` (`CampaignFiles`)."""
    from ._attach import attach_files

    return attach_files(
        files.tracker, robot_log=files.robot_log, mapping=files.mapping, robot=files.robot,
        tool=files.tool, program=files.program,
    )  # fmt: skip


def run(args: argparse.Namespace) -> int:
    from . import _output

    out = Path(args.out)
    _output.check(folders=[out], force=args.force)
    with _output.new_folder(out) as tmp:
        code = _run(args, tmp)
    print(f"results in {out}/")
    return code


def _run(args: argparse.Namespace, out: Path) -> int:

    from ..analysis import write_tum
    from ..analysis.discrepancy import discover
    from ..estimate import base_frame_poses, errors_against, estimate_poses, write_poses
    from ..estimate.calibration import fit
    from ..recording import write_recording
    from ..report import Section, recording_report, weighting_figure
    from ..sim import CONTROLLER_EPOCH, simulate, write_campaign
    from ._deviation import deviation_of
    from ._iso9283 import iso_of, print_table

    step = _Steps()
    hidden = ", ".join(f"{k}={v:g}" for k, v in HIDDEN.items())

    # 1. one setup (same seed: same camera placement, tool and robot), two recordings,
    # each split into what a lab has (tracker stream, joint log on the controller's
    # clock, URDF, tool, program) and joined again as `robtraj attach` does
    sims = {
        "calibration": simulate(
            "calibration", seed=args.seed, duration=40.0, rate=RATE, effects=HIDDEN
        ),
        "iso_cube": simulate("iso_cube", seed=args.seed, duration=60.0, rate=RATE, effects=HIDDEN),
    }
    truth = {k: r.truth for k, r in sims.items()}
    step(
        f"simulated a calibration run ({sims['calibration'].n_frames} frames) and an ISO cube "
        f"test ({sims['iso_cube'].n_frames} frames) at {RATE:g} Hz, 18 LEDs; hidden in the "
        f"robot: {hidden}"
    )
    (out / "campaign").mkdir()
    attached = {}
    for name, sim in sims.items():
        files = write_campaign(sim, out / "campaign", name=name)
        rec, alignment, _ = attach_campaign(files)
        write_recording(rec, out / f"{name}.h5", overwrite=True)
        attached[name] = rec
        step(
            f"{name}.h5 = campaign/{files.tracker.name} + {files.robot_log.name} + "
            f"{files.robot.name} + {files.tool.name} + {files.program.name}: robot clock "
            f"+{alignment.offset - CONTROLLER_EPOCH:.4f} s after the epoch (σ "
            f"{alignment.sigma * 1e3:.2f} ms; true {files.clock_offset - CONTROLLER_EPOCH:.4f} s)"
        )
    cal_rec, iso_rec = attached["calibration"], attached["iso_cube"]

    # 2. per-frame poses with LED-quality weighting
    est = estimate_poses(iso_rec, weighting="led_noise")
    write_poses(est, out / "poses.h5", recording="iso_cube.h5", overwrite=True)
    pe, _ = errors_against(
        est, truth["iso_cube"].tool_pose.position, truth["iso_cube"].tool_pose.quaternion_wxyz
    )
    step(
        f"poses.h5: {est.valid.mean() * 100:.1f} % of frames, median fit RMS "
        f"{np.nanmedian(est.rms) * 1e6:.1f} µm, error against the (hidden) truth "
        f"{np.sqrt(np.nanmean(pe**2)) * 1e6:.1f} µm RMS"
    )

    # 2b. the paper's Figure 4: uniform against quality weighting near the visibility edge
    paper = simulate("paper", seed=args.seed, duration=15.0, rate=RATE)
    tp = paper.truth.tool_pose
    ests = {}
    for scheme in ["uniform", "inverse_variance", "led_noise"]:
        e = estimate_poses(paper, weighting=scheme, constellation=paper.truth.constellation)
        ests[scheme] = e.position
        pe, _ = errors_against(e, tp.position, tp.quaternion_wxyz, gauge=False)
        step(f"paper trajectory, {scheme:>16}: {np.sqrt(np.nanmean(pe**2)) * 1e6:.1f} µm RMS")
    fig4 = weighting_figure(
        out / "report" / "weighting.png", paper.time, tp.position, ests,
        edge=(paper.status == 3).any(1),
    )  # fmt: skip

    # 3. nominal bundle calibration
    nominal = fit(cal_rec)
    (out / "calibration_nominal.json").write_text(json.dumps(nominal.to_json(), indent=1))
    step(
        f"calibration_nominal.json: residual RMS {nominal.residual_rms_m * 1e6:.1f} µm "
        f"(noise {nominal.noise_sigma_m * 1e6:.1f} µm): the model misses something"
    )

    # 4. discrepancy discovery on the calibration run
    disc = discover(cal_rec)
    doc = disc.to_json()
    (out / "discrepancy.json").write_text(json.dumps(doc, indent=1))
    named = [s["effect"] for s in doc["steps"]]
    step(
        f"discrepancy.json: gap {doc['gap_before_m'] * 1e6:.1f} µm → "
        f"{doc['gap_after_m'] * 1e6:.1f} µm; named: {', '.join(named) or 'nothing'}"
        + ("; unexplained structure remains" if doc["unexplained"] else "")
    )

    # 5. calibration with the named effects
    calib = fit(cal_rec, estimate=tuple(named)) if named else nominal
    (out / "calibration.json").write_text(json.dumps(calib.to_json(), indent=1))
    for name in named:
        step(f"calibration.json: {name}" + ("" if name in HIDDEN else " (not hidden)"))
        for line in effect_lines(calib, name, HIDDEN.get(name)):
            print(f"           {line}")

    # 6. ISO 9283 and path deviation of the cube test
    bf = base_frame_poses(iso_rec, calib)
    iso = iso_of(iso_rec, bf)
    (out / "iso9283.json").write_text(json.dumps(iso.to_json(), indent=1))
    ref, dev = deviation_of(iso_rec, bf)
    (out / "deviation.json").write_text(json.dumps(dev.summary().to_json(), indent=1))
    v = bf.valid
    write_tum(out / "measured.tum", bf.time, bf.position, bf.quaternion_wxyz, v)
    write_tum(out / "commanded.tum", bf.time, dev.foot, dev.foot_quaternion_wxyz, v)
    step("iso9283.json and deviation.json:")
    print_table(iso)

    # 7. the report
    disc_figs = disc.figures(out / "report") if hasattr(disc, "figures") else []
    extra = (
        Section(
            "Discrepancy discovery",
            f"Gap before {doc['gap_before_m'] * 1e6:.1f} µm, after "
            f"{doc['gap_after_m'] * 1e6:.1f} µm; named: {', '.join(named) or 'nothing'}. "
            f"(The demo hid {hidden}.)",
            figures=disc_figs,
        ),
        Section(
            "LED weighting (paper Figure 4)",
            "Error of the tool position against truth on the paper's trajectory (linear "
            "segment, reorientation in place, perpendicular segment), per weighting scheme; "
            "shaded: an LED near the edge of visibility.",
            figures=[fig4],
        ),
    )
    path = recording_report(
        out / "report", iso_rec, calib, bf, deviation=dev, reference=ref, iso=iso,
        extra_sections=extra, name="iso_cube.h5 (simulated)",
    )  # fmt: skip
    step(f"report: {Path(args.out) / path.relative_to(out)}")
    return 0
