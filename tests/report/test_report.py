"""The report writes legible PNGs and an HTML page that links them and holds the ISO tables."""

import re
from pathlib import Path

import numpy as np

from robtraj.report import (
    Section,
    Table,
    deviation_figure,
    iso_tables,
    path_3d_figure,
    pose_quality_figure,
    velocity_figure,
    visibility_figure,
    write_report,
)


def test_figures_and_html(tmp_path):
    rng = np.random.default_rng(0)
    n, m = 400, 12
    t = np.linspace(0, 4, n)
    pos = np.column_stack([np.cos(t), np.sin(t), 0.1 * t])
    dist = np.abs(rng.normal(0, 1e-4, n))
    err = np.abs(rng.normal(0, 1e-4, n))
    visible = rng.random((n, m)) > 0.2
    variance = np.where(visible, rng.random((n, m)) * 1e-10, np.nan)
    figs = tmp_path / "figs"
    pngs = [
        path_3d_figure(figs / "path_3d.png", pos, dist, reference=pos),
        deviation_figure(figs / "deviation.png", t * 0.1, dist, err, on_path=t > 0.5),
        velocity_figure(figs / "velocity.png", t, 0.1 + 0 * t, commanded=np.full(n, 0.1)),
        visibility_figure(
            figs / "visibility.png", t, visible, led_ids=np.arange(m) + 100, variance=variance
        ),  # fmt: skip
        pose_quality_figure(figs / "pose_quality.png", t, 3e-5 + 0 * t, visible.sum(1)),
    ]
    for p in pngs:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 5000
    iso = {
        "poses": {"P1": {"AP_mm": 0.12, "RP_mm": 0.034, "vAP_mm": None, "commanded_mm": [1, 2, 3]}},
        "paths": {},
    }
    sections = [
        Section("Path deviation", "Deviation along the path.", pngs[:3]),
        Section("Tracker", figures=pngs[3:]),
        Section("ISO 9283", tables=[*iso_tables(iso), Table("extra", ["a", "b"], [[1, 2.5]])]),
    ]
    out = tmp_path / "report"
    html_path = write_report(out, sections, name="cube run", date="2026-11-22")
    text = html_path.read_text()
    assert "cube run" in text and "2026-11-22" in text
    for src in re.findall(r'<img src="([^"]+)"', text):  # every image exists next to the page
        assert (out / src).is_file()
    assert len(re.findall(r"<img ", text)) == 5
    assert "<th>AP_mm</th>" in text and "<td>0.12</td>" in text and "commanded_mm" not in text
    assert Path(out / "path_3d.png").is_file()  # figures outside out_dir are copied in
