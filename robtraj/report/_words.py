"""Words for the report: column headers with units for the JSON keys, and the glossary."""

from __future__ import annotations

_UNITS = {
    "mm": "mm",
    "deg": "°",
    "s": "s",
    "percent": "%",
    "mm_per_s": "mm/s",
}

# JSON key (unit suffix removed) -> words with the standard's symbol as its own word
_LABELS = {
    "n_cycles": "cycles n",
    "n": "number of pairs or passes n",
    "n_frames": "frames on linear moves",
    "APx": "position accuracy AP, x component",
    "APy": "position accuracy AP, y component",
    "APz": "position accuracy AP, z component",
    "AP": "position accuracy AP",
    "RP": "position repeatability RP",
    "APa": "orientation accuracy AP, a (about x)",
    "APb": "orientation accuracy AP, b (about y)",
    "APc": "orientation accuracy AP, c (about z)",
    "AP_angle": "orientation accuracy AP, single angle",
    "RPa": "orientation repeatability RP, a (about x)",
    "RPb": "orientation repeatability RP, b (about y)",
    "RPc": "orientation repeatability RP, c (about z)",
    "RP_angle": "orientation repeatability RP, single angle",
    "vAP": "multi-directional variation vAP",
    "t_stab_mean": "stabilisation time t_stab, mean",
    "t_stab_max": "stabilisation time t_stab, max",
    "OV_mean": "overshoot OV, mean",
    "OV_max": "overshoot OV, max",
    "dAP": "drift of position accuracy dAP",
    "dRP": "drift of position repeatability dRP",
    "Dc": "commanded distance D_c",
    "AD": "distance accuracy AD",
    "RD": "distance repeatability RD",
    "length": "path length",
    "vc": "commanded speed v_c",
    "AT": "path accuracy AT",
    "RT": "path repeatability RT",
    "ATa": "path orientation accuracy AT, a (about x)",
    "ATb": "path orientation accuracy AT, b (about y)",
    "ATc": "path orientation accuracy AT, c (about z)",
    "AT_angle": "path orientation accuracy AT, single angle",
    "RTa": "path orientation repeatability RT, a (about x)",
    "RTb": "path orientation repeatability RT, b (about y)",
    "RTc": "path orientation repeatability RT, c (about z)",
    "v_mean": "mean speed",
    "AV": "velocity accuracy AV",
    "RV": "velocity repeatability RV",
    "FV": "velocity fluctuation FV",
    "CR_mean": "corner round-off CR, mean",
    "CR_max": "corner round-off CR, max",
    "CO_mean": "corner overshoot CO, mean",
    "CO_max": "corner overshoot CO, max",
    "distance_max": "distance to the commanded path, max",
    "distance_mean": "distance to the commanded path, mean",
    "distance_rms": "distance to the commanded path, RMS",
    "orientation_max": "orientation error, max",
    "orientation_mean": "orientation error, mean",
    "orientation_rms": "orientation error, RMS",
}


# captions of figures written under fixed names by other parts of the package (the demo,
# the discrepancy workflow) and passed to the report as plain paths
CAPTIONS = {
    "discrepancy_gap": "Gap between model and measurement (systematic RMS) after each named "
    "effect is added, against the per-axis noise and the gap a complete model leaves by "
    "chance.",
    "discrepancy_structure": "Residual RMS against time, joint angle and LED emission angle, "
    "with the nominal model and with the named effects: structure that remains is what the "
    "model still misses.",
    "weighting": "Error of the tool position against the simulation's truth per LED weighting "
    "scheme (25-frame moving mean), per axis; shaded: an LED at the edge of visibility.",
}


def column_label(key: str) -> str:
    """Words and unit for a JSON key such as ``"t_stab_mean_s"`` → ``"stabilisation time
    t_stab, mean [s]"``; an unknown key is shown as it is, its unit suffix in brackets."""
    for suffix in sorted(_UNITS, key=len, reverse=True):
        if key.endswith("_" + suffix):
            stem = key[: -len(suffix) - 1]
            return f"{_LABELS.get(stem, stem)} [{_UNITS[suffix]}]"
    return _LABELS.get(key, key)


GLOSSARY = {
    "AP": "accuracy: distance between the mean attained pose (barycentre of the cycles) and "
    "the commanded pose (ISO 9283 §7.2.1); for orientation the mean of the a, b, c errors "
    "or the single rotation angle between mean attained and commanded orientation.",
    "RP": "repeatability: l̄ + 3·S_l, the mean distance of the attained positions from "
    "their barycentre plus three sample standard deviations (§7.2.2); for orientation "
    "3·S per component, or the mean + 3·S of the single angle to the mean orientation.",
    "vAP": "multi-directional pose accuracy variation: largest distance between the "
    "barycentres of attainments approached from different directions (§7.3).",
    "t_stab": "stabilisation time: from first entering the limit band (RP around the "
    "attained pose) until the robot stays inside it (§7.5).",
    "OV": "overshoot: largest distance from the attained pose after first entering the "
    "limit band, 0 when it never leaves (§7.6).",
    "dAP": "drift of AP: |AP(last cycles) − AP(first cycles)| (§7.7).",
    "dRP": "drift of RP: |RP(last cycles) − RP(first cycles)| (§7.7).",
    "D_c": "commanded distance between two test poses.",
    "AD": "distance accuracy: mean attained distance minus commanded distance (§7.4).",
    "RD": "distance repeatability: 3·S of the attained distances (§7.4).",
    "AT": "path accuracy: largest distance, over planes normal to the commanded line, "
    "between the barycentre of the passes and the commanded path (§8.2).",
    "RT": "path repeatability: largest l̄ + 3·S_l over the normal planes (§8.3).",
    "v_c": "commanded TCP speed of the move.",
    "AV": "velocity accuracy: (mean speed − commanded speed) / commanded speed (§8.6).",
    "RV": "velocity repeatability: 3·S of the per-pass mean speed / commanded speed.",
    "FV": "velocity fluctuation: largest (max − min) speed within one pass.",
    "CR": "corner round-off: closest approach of the measured path to the corner (§8.5).",
    "CO": "corner overshoot: largest deviation from the second leg in its first half.",
    "a": "a, b, c: rotation of the orientation error R_attained · R_commandedᵀ about the "
    "base x, y, z axes.",
    "n": "number of cycles (attainments of a pose, passes of a path) a figure comes from; "
    "ISO 9283 asks for 30 cycles.",
    "RMS": "root mean square.",
    "σ": "standard deviation of an estimate, from the calibration's covariance.",
    "τ": "clock offset between robot and tracker (robot clock minus tracker clock).",
    "[lo, hi]": "95 % confidence interval of a characteristic, from the scatter of the cycles.",
}
