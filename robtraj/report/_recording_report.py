"""The customer report of one recording: ISO table, path, deviation, speed, LEDs, quality."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._figures import (
    deviation_figure,
    path_3d_figure,
    pose_quality_figure,
    velocity_figure,
    visibility_figure,
)
from ._html import Section, Table, iso_tables, write_report


def recording_report(
    out_dir: str | os.PathLike,
    rec,
    calibration,
    base_poses,
    *,
    deviation=None,
    reference=None,
    iso=None,
    extra_sections: tuple[Section, ...] = (),
    name: str = "recording",
) -> Path:
    """Write `out_dir/report.html` with its PNGs.

    `base_poses` from `robtraj.estimate._base_frame.base_frame_poses`; `deviation` (a
    `DeviationResult`) and `reference` (its `ReferencePath`) and `iso` (an
    `Iso9283Result`) when they could be computed.
    """
    from ..estimate import chunked_led_variance

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    est = base_poses.poses
    t = base_poses.time
    sections = []
    c = calibration
    cal_rows = [
        [
            "camera←base position [mm]",
            np.round(np.asarray(c.camera_from_base.position) * 1e3, 3).tolist(),
        ],
        [
            "flange←tool position [mm]",
            np.round(np.asarray(c.flange_from_tool.position) * 1e3, 3).tolist(),
        ],
        ["residual RMS [µm]", round(c.residual_rms_m * 1e6, 2)],
        ["gauge", c.gauge],
        ["estimated effects", ", ".join(c.estimated) or "none"],
        ["clock offset τ [ms]", round(c.time_offset * 1e3, 4)],
    ]
    sections.append(
        Section(
            "Calibration",
            "Bundle calibration of camera←base, flange←tool and the LED constellation "
            "(robtraj calibrate).",
            tables=[Table("Calibration", ["quantity", "value"], cal_rows)],
        )
    )
    if iso is not None:
        sections.append(
            Section(
                "ISO 9283 characteristics",
                "Measured TCP (the controller's TCP carried by the measured flange) against "
                "the program. Positions in mm, angles in degrees.",
                tables=iso_tables(iso.to_json()),
            )
        )
    if deviation is not None:
        figs = [
            path_3d_figure(
                out / "path_3d.png",
                base_poses.position,
                deviation.distance,
                reference=None if reference is None else reference.position,
            ),
            deviation_figure(
                out / "deviation.png",
                deviation.progress,
                deviation.distance,
                deviation.orientation_error,
                on_path=deviation.on_path,
            ),
        ]
        s = deviation.summary().to_json()
        sections.append(
            Section(
                "Path deviation",
                "Point-to-segment distance to the commanded path (monotone match in path "
                "progress) and the single-angle orientation error at the foot point.",
                figures=figs,
                tables=[
                    Table(
                        "Deviation summary", ["quantity", "value"], [[k, v] for k, v in s.items()]
                    )
                ],
            )
        )
    speed = np.linalg.norm(np.gradient(base_poses.position, t, axis=0), axis=1)
    sections.append(Section("TCP speed", figures=[velocity_figure(out / "speed.png", t, speed)]))
    variance = chunked_led_variance(np.asarray(rec.positions), est.window, "paper")
    sections.append(
        Section(
            "LED visibility and variance (paper Figure 3)",
            figures=[
                visibility_figure(
                    out / "leds.png", rec.time, rec.visible, led_ids=rec.led_ids, variance=variance
                )
            ],
        )
    )
    sections.append(
        Section(
            "Pose quality",
            f"Per-frame weighted residual RMS and LEDs used ({est.weighting} weighting).",
            figures=[pose_quality_figure(out / "pose_quality.png", t, est.rms, est.n_used)],
        )
    )
    sections.extend(extra_sections)
    return write_report(
        out, sections, name=name, date=str(rec.attrs.get("created", ""))[:10] or None
    )
