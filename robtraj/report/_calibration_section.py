"""The calibration in a recording's report: its rigid transforms, quality and fitted
effects with σ, and its line and warnings in the summary."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..model import effect_component_names
from ._html import Section, Table
from ._report_part import ReportPart, left_out

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


def calibration_part(c) -> ReportPart:
    """The calibration's section and summary line (residual, noise, effects, what could
    not be identified), with warnings when it did not converge or held parameters at
    zero; left out without a calibration."""
    if c is None:
        part = left_out("Calibration", "no calibration (needs a robot log, or --calibration).")
        return dataclasses.replace(part, facts=(("calibration", "none"),))
    dropped = [d["parameter"] for d in c.identifiability.get("dropped", [])]
    fact = (
        "calibration",
        f"residual RMS {_micro(c.residual_rms_m, 1, ' µm')} (noise σ per axis "
        f"{_micro(c.noise_sigma_m, 1, ' µm')}); effects: "
        + (", ".join(c.estimated) or "none")
        + "; fixed (not identifiable): "
        + (", ".join(dropped) or "none"),
    )
    warnings = []
    if c.iterations and not c.converged:
        warnings.append("the calibration did not converge")
    if dropped:
        warnings.append(
            "calibration parameters not identifiable from the data, held at zero: "
            + ", ".join(dropped)
        )
    return ReportPart(
        Section("Calibration", tables=calibration_tables(c)), (fact,), tuple(warnings)
    )
