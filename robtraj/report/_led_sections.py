"""The LEDs in a recording's report: which the camera saw, their moving-window variance,
and the noise model estimated from the recording."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._errors import UserError
from ._discrepancy_figures import noise_figure
from ._figures import most_changing, visibility_figure
from ._html import Figure, Section, Table
from ._report_part import ReportPart, left_out
from ._tool_poses import ToolPoses


def led_part(out: Path, rec, poses: ToolPoses) -> ReportPart:
    """LED visibility over time and the moving-window LED variance of the paper's Figure 3
    (figure `out/leds.png`), over the pose fit's window (the default window without
    poses). The positions are read chunk by chunk (`rec` may be opened lazily); of the
    variance, only the three LEDs the figure shows are kept."""
    from ..estimate import chunked_led_variance, default_window, visible_frames

    est = poses.estimate
    window = est.window if est is not None else default_window(np.asarray(rec.time))
    visible = visible_frames(rec.positions)
    pick = most_changing(visible)
    variance = chunked_led_variance(rec.positions, window, "paper", keep=pick)
    return ReportPart(
        Section(
            "LED visibility and variance (paper Figure 3)",
            figures=[
                Figure(
                    visibility_figure(
                        out / "leds.png",
                        rec.time,
                        visible,
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


def noise_part(out: Path, rec) -> ReportPart:
    """The recording's noise model (`robtraj.estimate.observation_noise_source`, read
    chunk by chunk): figure and the σ table at its knots; left out with the reason when
    it cannot be estimated."""
    from ..estimate import observation_noise_source

    title = "Noise of the recording"
    if rec.tool is None:
        return left_out(title, "no tool constellation: the LEDs' rigid pairs are unknown.")
    try:
        model, _ = observation_noise_source(rec)
    except UserError as e:
        return left_out(title, f"{e}.")
    sigma = np.sqrt(model.variance) * 1e6
    head = ["emission angle [°]"] + [f"σ at {r:.2f} m [µm]" for r in model.distance_knots]
    rows = [
        [f"{np.degrees(a):.0f}", *(float(x) for x in row)]
        for a, row in zip(model.angle_knots, sigma)
    ]
    section = Section(
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
    return ReportPart(section)
