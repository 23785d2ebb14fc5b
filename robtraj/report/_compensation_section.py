"""The report's "Accuracy after compensation (predicted)": per ISO 9283 test pose, the AP
measured now and the AP predicted once the program is compensated with the calibration
(`robtraj.analysis.accuracy_after_compensation`), with the calibration's σ."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..analysis import accuracy_after_compensation
from ._figures import compensation_figure
from ._html import Figure, Section, Table
from ._report_part import ReportPart


def compensation_part(out: Path, rec, calibration, iso) -> ReportPart:
    """The section, and the summary's worst predicted AP; nothing without an ISO pose
    test and a calibration."""
    if iso is None or calibration is None:
        return ReportPart()
    pred = accuracy_after_compensation(rec, calibration, iso)
    if pred is None:
        return ReportPart()
    now = np.linalg.norm(pred.error_now, axis=1)
    after = np.linalg.norm(pred.error_after, axis=1)
    rows = [
        [n, a * 1e3, b * 1e3, s * 1e3]
        for n, a, b, s in zip(pred.names, now, after, pred.sigma_after)
    ]
    worst = int(np.argmax(after))
    fact = (
        f"AP after compensation, predicted, worst ({pred.names[worst]})",
        f"{after[worst] * 1e3:.3f} mm (now {now[worst] * 1e3:.3f} mm)",
    )
    section = Section(
        "Accuracy after compensation (predicted)",
        "What `robtraj compensate` with this calibration would leave, predicted from this "
        "recording (no compensated run was measured): per test pose, the measured AP "
        "minus the correction the calibrated model makes at the command. What the model "
        "does not describe and the controller's own positioning error remain. σ is the "
        "calibration's uncertainty carried to the predicted AP vector (per axis); the "
        "repeatability of the attainments comes on top.",
        figures=[
            Figure(
                compensation_figure(
                    out / "compensation.png", pred.names, now, after, pred.sigma_after
                ),
                "AP per test pose, measured now and predicted after compensation (±2σ).",
            )
        ],
        tables=[
            Table(
                "AP now and after compensation",
                ["pose", "AP now [mm]", "AP after, predicted [mm]", "σ per axis [mm]"],
                rows,
                "AP = distance of the barycentre of the attained positions from the command.",
            )
        ],
    )
    return ReportPart(section, (fact,))
