"""The test report of one recording: summary, calibration, ISO 9283 tables, path deviation,
speed, LEDs and pose quality. Sections whose inputs are absent are left out with a note."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import UserError
from ..model import effect_component_names
from ._discrepancy_figures import noise_figure
from ._figures import (
    deviation_figure,
    path_3d_figure,
    pose_quality_figure,
    static_pose_figure,
    velocity_figure,
    visibility_figure,
)
from ._html import Figure, Section, Summary, Table, Value, interval_of, iso_tables, write_report
from ._words import column_label

ISO_CYCLES = 30  # cycles ISO 9283 §6.6 asks for per test

# effect -> (display unit, factor from SI)
_EFFECT_UNITS = {
    "time_offset": ("ms", 1e3),
    "joint_offset": ("µrad", 1e6),
    "link_length": ("µm", 1e6),
    "link_twist": ("µrad", 1e6),
    "joint_compliance": ("µrad/(N·m)", 1e6),
    "backlash": ("µrad", 1e6),
    "led_angle_bias": ("µm", 1e6),
    "tracker_scale": ("ppm", 1e6),
    "thermal_drift": ("µm/K", 1e6),
}
# key characteristics in the summary: (block, key), the worst entry of the block
_KEY_CHARACTERISTICS = [
    ("poses", "AP_mm"),
    ("poses", "RP_mm"),
    ("poses", "AP_angle_deg"),
    ("poses", "RP_angle_deg"),
    ("distances", "AD_mm"),
    ("distances", "RD_mm"),
    ("paths", "AT_mm"),
    ("paths", "RT_mm"),
    ("corners", "CR_max_mm"),
]


def _pose_rows(label: str, pose, sigma: Mapping[str, float], prefix: str) -> list[list[Any]]:
    from scipy.spatial.transform import Rotation

    pos = np.asarray(pose.position) * 1e3
    rv = np.degrees(Rotation.from_quat(pose.quaternion_wxyz, scalar_first=True).as_rotvec())
    s_t = [sigma.get(f"{prefix}.t{a}", np.nan) * 1e3 for a in "xyz"]
    s_r = [np.degrees(sigma.get(f"{prefix}.r{a}", np.nan)) for a in "xyz"]
    return [
        [f"{label} position x, y, z", _join(pos, 3), _join(s_t, 4), "mm"],
        [f"{label} rotation vector x, y, z", _join(rv, 4), _join(s_r, 5), "°"],
    ]


def _join(values, decimals: int) -> str:
    """``"a, b, c"`` with fixed decimals; "–" when none is finite."""
    v = np.asarray(values, float)
    return ", ".join(f"{x:.{decimals}f}" for x in v) if np.isfinite(v).any() else "–"


def _micro(x: float, decimals: int = 2, unit: str = "") -> str:
    """Metres as µm text (with `unit` appended), "not given" for NaN."""
    return f"{x * 1e6:.{decimals}f}{unit}" if np.isfinite(x) else "not given"


def calibration_tables(c) -> list[Table]:
    """The calibration's rigid transforms and quality, and its fitted effects with σ."""
    sigma = c.sigma if np.size(c.covariance) else {}
    dropped = [d["parameter"] for d in c.identifiability.get("dropped", [])]
    tau = (
        f"{c.time_offset * 1e3:.4f} (σ {sigma.get('time_offset', np.nan) * 1e3:.2g} ms)"
        if "time_offset" in c.estimated
        else "not estimated"
    )
    rows = [
        *_pose_rows("camera←base", c.camera_from_base, sigma, "camera_from_base"),
        *_pose_rows("flange←tool", c.flange_from_tool, sigma, "flange_from_tool"),
        ["residual RMS of the LED positions", _micro(c.residual_rms_m), "", "µm"],
        ["noise σ per axis", _micro(c.noise_sigma_m), "", "µm"],
        ["clock offset τ", tau, "", "ms"],
        [
            "converged",
            f"{c.converged} after {c.iterations} iterations" if c.iterations else "not given",
            "",
            "",
        ],
        ["parameters fixed (not identifiable)", ", ".join(dropped) or "none", "", ""],
        ["LEDs never seen", ", ".join(map(str, c.unseen_leds)) or "none", "", ""],
        ["gauge", c.gauge, "", ""],
    ]
    out = [
        Table(
            "Calibration",
            ["quantity", "value", "σ", "unit"],
            rows,
            "Bundle calibration (robtraj calibrate): camera←base and flange←tool as position "
            "and rotation vector; σ from the calibration's covariance (right perturbation, "
            "tool/base axes)"
            + ("" if sigma else "; the calibration has no covariance, so no σ")
            + ". Fixed parameters could not be told apart from others and are held at zero.",
        )
    ]
    effects = [e for e in c.estimated if e != "time_offset"]
    if effects:
        fixed = set(c.identifiability.get("fixed_parameters", [])) | set(dropped)
        rows = []
        for name in effects:
            value = np.asarray(c.effects[name], float)
            unit, f = _EFFECT_UNITS.get(name, ("SI", 1.0))
            for comp, v in zip(effect_component_names(name, value.shape), value.ravel()):
                s = sigma.get(comp, np.nan)
                if comp in fixed:
                    rows.append([comp, "fixed (not identifiable)", "–", "–", unit])
                    continue
                z = abs(v) / s if s > 0 else np.nan
                rows.append([comp, v * f, s * f, z, unit])
        out.append(
            Table(
                "Fitted effects",
                ["parameter", "value", "σ", "|value| / σ", "unit"],
                rows,
                "Effects estimated beside the rigid transforms, with their standard deviation; "
                "|value| / σ above about 3 means the effect is clearly present.",
            )
        )
    return out


_WHY = {
    "vAP": "vAP needs approaches from several directions",
    "dAP": "drift needs at least 4 cycles",
    "dRP": "drift needs at least 4 cycles",
}


def _symbol(key: str) -> str:
    """The characteristic's symbol of a JSON key: ``"t_stab_mean_s"`` → ``"t_stab_mean"``."""
    for suffix in ("_mm_per_s", "_percent", "_deg", "_mm", "_s"):
        if key.endswith(suffix):
            return key[: -len(suffix)]
    return key


def _key_facts(iso_json: Mapping[str, Any]) -> tuple[list[tuple[str, Any]], list[str]]:
    """Summary rows (worst pose/path per characteristic, with its interval) and warnings
    (too few cycles, characteristics without a value)."""
    facts, warnings = [], []
    for block, key in _KEY_CHARACTERISTICS:
        entries = {n: v for n, v in iso_json.get(block, {}).items() if v.get(key) is not None}
        if not entries:
            continue
        name = max(entries, key=lambda n: abs(entries[n][key]))
        facts.append(
            (
                f"{column_label(key)}, worst ({name})",
                Value(entries[name][key], interval_of(entries[name], key)),
            )
        )
    for block in ("poses", "paths"):
        cycles = {n: v.get("n_cycles") for n, v in iso_json.get(block, {}).items()}
        cycles = {n: c for n, c in cycles.items() if c}
        if cycles and min(cycles.values()) < ISO_CYCLES:
            lo, hi = min(cycles.values()), max(cycles.values())
            span = f"{lo}" if lo == hi else f"{lo}–{hi}"
            warnings.append(
                f"ISO 9283 {block}: {span} cycles per {block[:-1]}, the standard asks for "
                f"{ISO_CYCLES}; the characteristics scatter more than in a full test."
            )
        entries = iso_json.get(block, {})
        empty = [n for n, v in entries.items() if v.get("n_cycles") == 0]
        if empty:
            warnings.append(
                f"ISO 9283 {block} {', '.join(empty)}: no complete cycle measured, so no "
                "characteristics."
            )
        missing: dict[tuple[str, ...], list[str]] = {}
        for k in {k for n, v in entries.items() if n not in empty for k in v}:
            names = tuple(n for n, v in entries.items() if n not in empty and v.get(k, 0) is None)
            if names:
                missing.setdefault(names, []).append(_symbol(k))
        for names, keys in missing.items():
            warnings.append(
                f"ISO 9283 {block} {', '.join(names)}: no value (NaN) for "
                f"{', '.join(sorted(keys))}"
                + "".join(
                    f" ({w})" for w in dict.fromkeys(_WHY[k] for k in sorted(keys) if k in _WHY)
                )
                + "."
            )
    return facts, warnings


def static_pose_errors(rec, calibration, base_poses) -> tuple[np.ndarray, np.ndarray] | None:
    """Position error [m] and single rotation angle [rad] per frame of a static pose
    series (one robot log sample per tracker frame at the same time, no linear move, no
    segment map: an imported 6-DOF pose series): the measured flange, base←tool ·
    (flange←tool)⁻¹ through the calibration, against the flange pose the robot model
    (with the calibration's effects) gives for the logged joints. None for any other
    recording."""
    import jax.numpy as jnp
    from scipy.spatial.transform import Rotation

    from ..analysis import absolute_pose_error
    from ..model import flange_poses, robot_from_log

    prog, log = rec.program, rec.robot
    if (
        calibration is None
        or base_poses is None
        or log is None
        or (prog is not None and prog.segment is not None)
        or (prog is not None and np.any(np.asarray(prog.motion).astype(str) == "linear"))
        or np.shape(log.joints)[0] != rec.n_frames
        or not np.allclose(log.time, rec.time)
    ):
        return None
    q = jnp.asarray(log.joints, jnp.float64)
    cmd = flange_poses(
        robot_from_log(log),
        calibration.effects_module(q.shape[1]),
        q,
        jnp.zeros_like(q),
    ).wxyz_xyz
    cmd = np.asarray(cmd)
    ft = calibration.flange_from_tool
    r_ft = Rotation.from_quat(ft.quaternion_wxyz, scalar_first=True)
    ok = base_poses.valid
    r_bt = Rotation.from_quat(np.where(ok[:, None], base_poses.quaternion_wxyz, [1, 0, 0, 0]),
                              scalar_first=True)  # fmt: skip
    p_bf = base_poses.position - r_bt.apply(r_ft.inv().apply(ft.position))
    q_bf = (r_bt * r_ft.inv()).as_quat(scalar_first=True)
    p_bf[~ok], q_bf[~ok] = np.nan, np.nan
    return absolute_pose_error(p_bf, q_bf, cmd[:, 4:], cmd[:, :4])


def _noise_section(out: Path, rec) -> Section:
    """The recording's noise model (`robtraj.estimate.observation_noise`): figure and the
    σ table at its knots; left out with the reason when it cannot be estimated."""
    from ..estimate import observation_noise

    title = "Noise of the recording"
    if rec.tool is None:
        return _left_out(title, "no tool constellation: the LEDs' rigid pairs are unknown.")
    try:
        model, _ = observation_noise(rec)
    except UserError as e:
        return _left_out(title, f"{e}.")
    sigma = np.sqrt(model.variance) * 1e6
    head = ["emission angle [°]"] + [f"σ at {r:.2f} m [µm]" for r in model.distance_knots]
    rows = [
        [f"{np.degrees(a):.0f}", *(float(x) for x in row)]
        for a, row in zip(model.angle_knots, sigma)
    ]
    return Section(
        title,
        "Per-axis LED noise estimated from the recording alone: the distance between two "
        "LEDs of the rigid tool does not change as it moves, so its second difference over "
        "three frames is noise. σ is modelled as a function of the LED's emission angle, "
        "its distance from the camera and the LED's own level; every calibration weight "
        "and the discrepancy workflow's gap and floor use it. Level of the model ±"
        f"{100 * model.level_rel_se:.1f} % (jackknife over time blocks).",
        figures=[
            Figure(
                noise_figure(out / "noise_model.png", model),
                "Noise σ per axis against the emission angle (at the distance knots) and "
                "against the distance (at three angles); right: each LED's variance level "
                "(1 = the recording's mean).",
            )
        ],
        tables=[Table("Noise model", head, rows, "σ per axis at the model's knots.")],
    )


def _left_out(title: str, reason: str) -> Section:
    return Section(title, f"Left out: {reason}")


def recording_report(
    out_dir: str | os.PathLike,
    rec,
    calibration=None,
    base_poses=None,
    *,
    deviation=None,
    reference=None,
    iso=None,
    extra_sections: tuple[Section, ...] = (),
    name: str = "recording",
    notes: Sequence[str] = (),
) -> Path:
    """Write `out_dir/report.html` with its PNGs.

    `calibration` (a `CalibrationResult`) and `base_poses` (from
    `robtraj.estimate._base_frame.base_frame_poses`) when the recording could be put into
    the robot base frame; without them the tool poses are fitted in the camera frame (when
    the recording has a tool) and the calibration section is left out. `deviation` (a
    `DeviationResult`) with `reference` (its `ReferencePath`) and `iso` (an
    `Iso9283Result`) when they could be computed; `notes` (why something was left out)
    go to the summary's warnings.
    """
    from ..estimate import chunked_led_variance, default_window, estimate_poses

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    warnings = list(notes)
    if base_poses is not None:
        est, t, position = base_poses.poses, base_poses.time, base_poses.position
        frame = "robot base frame"
    elif rec.tool is not None:
        try:
            est = estimate_poses(rec)
            t, position = est.time, est.position
            frame = "camera (tracker) frame, no calibration to the robot base"
        except UserError as e:
            est = t = position = None
            frame = "none: the tool poses could not be fitted"
            warnings.append(f"tool poses left out: {e}")
    else:
        est = t = position = None
        frame = "none: the recording has no tool constellation"
        warnings.append("no tool constellation: only the LED data are reported")

    duration = float(rec.time[-1] - rec.time[0]) if rec.n_frames > 1 else 0.0
    robot = rec.robot
    facts: list[tuple[str, Any]] = [
        (
            "recording",
            f"{name}: {rec.n_frames} frames over {duration:.1f} s, {rec.n_leds} LEDs"
            + (f", source {rec.attrs['source']}" if rec.attrs.get("source") else ""),
        ),
        (
            "robot",
            "no robot log"
            if robot is None
            else f"{robot.model or 'DH table'}, {np.shape(robot.joints)[1]} joints, "
            f"{np.shape(robot.joints)[0]} log samples",
        ),
        (
            "tool",
            "no tool constellation"
            if rec.tool is None
            else f"{len(rec.tool.led_ids)} LEDs"
            + (
                ", nominal TCP flange←tool at "
                + ", ".join(
                    f"{x:.2f}" for x in np.asarray(rec.tool.flange_from_tool.position) * 1e3
                )
                + " mm"
                if rec.tool.flange_from_tool is not None
                else ", no nominal TCP"
            ),
        ),
        ("poses", frame),
    ]
    if est is not None:
        facts.append(
            (
                "pose fit",
                f"{est.valid.mean() * 100:.1f} % of frames, median fit RMS "
                f"{np.nanmedian(est.rms) * 1e6:.1f} µm ({est.weighting} weighting)",
            )
        )
    c = calibration
    if c is not None:
        dropped = [d["parameter"] for d in c.identifiability.get("dropped", [])]
        facts.append(
            (
                "calibration",
                f"residual RMS {_micro(c.residual_rms_m, 1, ' µm')} (noise σ per axis "
                f"{_micro(c.noise_sigma_m, 1, ' µm')}); effects: "
                + (", ".join(c.estimated) or "none")
                + "; fixed (not identifiable): "
                + (", ".join(dropped) or "none"),
            )
        )
        if c.iterations and not c.converged:
            warnings.append("the calibration did not converge")
        if dropped:
            warnings.append(
                "calibration parameters not identifiable from the data, held at zero: "
                + ", ".join(dropped)
            )
    else:
        facts.append(("calibration", "none"))

    sections = []
    if c is not None:
        sections.append(Section("Calibration", tables=calibration_tables(c)))
    else:
        sections.append(
            _left_out("Calibration", "no calibration (needs a robot log, or --calibration).")
        )

    static = static_pose_errors(rec, c, base_poses)
    if static is not None:
        e, a = static
        ok = np.isfinite(e)
        e, a = e[ok], a[ok]
        rms = lambda x: float(np.sqrt(np.mean(x**2)))  # noqa: E731
        facts.append(
            (
                "static pose error",
                f"position RMS {rms(e) * 1e3:.3f} mm, max {e.max() * 1e3:.3f} mm; orientation "
                f"RMS {np.degrees(rms(a)):.4f}° over {e.size} poses",
            )
        )
        rows = [
            ["poses", e.size, "–"],
            ["position error, mean", e.mean() * 1e3, "mm"],
            ["position error, RMS", rms(e) * 1e3, "mm"],
            ["position error, max", e.max() * 1e3, "mm"],
            ["orientation error, mean", np.degrees(a.mean()), "°"],
            ["orientation error, RMS", np.degrees(rms(a)), "°"],
            ["orientation error, max", np.degrees(a.max()), "°"],
        ]
        sections.append(
            Section(
                "Static pose accuracy",
                "Measured flange pose (the measured tool pose through the calibration's "
                "camera←base and flange←tool) against the flange pose of the robot model "
                "for the logged joint angles (nominal kinematics plus the calibrated "
                "effects), pose by pose. The calibration fits the rigid transforms to these "
                "same poses, so this is what the model leaves unexplained; ISO 9283 AP/RP "
                "need repeated cycles.",
                figures=[
                    Figure(
                        static_pose_figure(out / "static_poses.png", *static),
                        "Position and orientation error of each static pose against the "
                        "robot model, and their distribution.",
                    )
                ],
                tables=[
                    Table(
                        "Static pose errors",
                        ["quantity", "value", "unit"],
                        rows,
                        "Over the poses where the tool was seen.",
                    )
                ],
            )
        )

    if iso is not None:
        iso_json = iso.to_json()
        key, iso_warn = _key_facts(iso_json)
        facts += key
        warnings += iso_warn
        sections.append(
            Section(
                "ISO 9283 characteristics",
                "Measured TCP (the controller's TCP carried by the measured flange) against "
                "the program, per test pose and repeated path; value [lo, hi] where a 95 % "
                "confidence interval from the cycles is available.",
                tables=iso_tables(iso_json),
            )
        )
    else:
        sections.append(
            _left_out(
                "ISO 9283 characteristics",
                "needs a program (/program) with repeated poses or moves and base-frame "
                "poses; see the notes in the summary.",
            )
        )

    if deviation is not None:
        s = deviation.summary()
        facts.append(
            (
                "path deviation",
                f"RMS {s.distance_rms * 1e3:.3f} mm, max {s.distance_max * 1e3:.3f} mm; "
                f"orientation RMS {np.degrees(s.orientation_rms):.4f}° over {s.n} frames "
                "on linear moves",
            )
        )
        figs = [
            Figure(
                path_3d_figure(
                    out / "path_3d.png",
                    position,
                    deviation.distance,
                    reference=None if reference is None else reference.position,
                ),
                "Measured TCP path (points coloured by their distance to the commanded path) "
                "and the commanded path (red, dashed, drawn on top); left in 3D, right seen "
                "from above.",
            ),
            Figure(
                deviation_figure(
                    out / "deviation.png",
                    deviation.progress,
                    deviation.distance,
                    deviation.orientation_error,
                    on_path=deviation.on_path,
                ),
                "Distance to the commanded path and orientation error against path "
                "progress; grey: frames on joint moves, where the path is not specified.",
            ),
        ]
        sj = s.to_json()
        sections.append(
            Section(
                "Path deviation",
                "Point-to-segment distance to the commanded path (match monotone in path "
                "progress) and the single-angle orientation error at the foot point.",
                figures=figs,
                tables=[
                    Table(
                        "Deviation summary",
                        ["quantity", "value"],
                        [[column_label(k), v] for k, v in sj.items()],
                        "Over the seen frames on linear moves.",
                    )
                ],
            )
        )
    else:
        sections.append(
            _left_out(
                "Path deviation",
                "needs a program with linear moves and base-frame poses; see the notes in "
                "the summary.",
            )
        )

    if est is not None:
        speed = np.linalg.norm(np.gradient(position, t, axis=0), axis=1) if t.size > 1 else t * 0
        sections.append(
            Section(
                "TCP speed",
                figures=[
                    Figure(
                        velocity_figure(out / "speed.png", t, speed),
                        f"Speed of the measured tool point ({frame}), central differences "
                        "between frames.",
                    )
                ],
            )
        )
    window = est.window if est is not None else default_window(np.asarray(rec.time))
    variance = chunked_led_variance(np.asarray(rec.positions), window, "paper")
    sections.append(
        Section(
            "LED visibility and variance (paper Figure 3)",
            figures=[
                Figure(
                    visibility_figure(
                        out / "leds.png",
                        rec.time,
                        rec.visible,
                        led_ids=rec.led_ids,
                        variance=variance,
                    ),
                    f"Top: which LED the camera saw (black) over time. Bottom: moving-window "
                    f"LED variance ({window} frames) of the three LEDs whose visibility changes "
                    "most, as a standard deviation; the axis is clipped at the median + 10 "
                    "robust standard deviations (1.4826 · MAD) so that spikes (marked ▼, "
                    "counted in the legend) do not hide the normal level.",
                )
            ],
        )
    )
    sections.append(_noise_section(out, rec))
    if est is not None:
        sections.append(
            Section(
                "Pose quality",
                figures=[
                    Figure(
                        pose_quality_figure(out / "pose_quality.png", t, est.rms, est.n_used),
                        f"Per-frame weighted residual RMS of the tool pose fit ({est.weighting} "
                        "weighting) and the number of LEDs it used.",
                    )
                ],
            )
        )
    sections.extend(extra_sections)
    return write_report(
        out,
        sections,
        name=name,
        date=str(rec.attrs.get("created", ""))[:10] or None,
        summary=Summary(facts, warnings),
        title="Robot performance test report (ISO 9283)",
    )
