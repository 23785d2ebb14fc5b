"""The report writes legible PNGs and an HTML page that links them and holds the ISO tables."""

import re
from pathlib import Path

import numpy as np
import pytest

from robtraj.report import (
    Section,
    Table,
    Value,
    deviation_figure,
    interval_of,
    iso_tables,
    path_3d_figure,
    pose_quality_figure,
    robust_limit,
    velocity_figure,
    visibility_figure,
    write_report,
)
from robtraj.report._calibration_section import calibration_tables
from robtraj.report._html import _cell
from robtraj.report._static_pose_section import static_pose_errors
from robtraj.report._words import column_label


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
    # transposed: one row per characteristic, in words with the unit; lists left out
    assert "<td>position accuracy AP [mm]</td><td>0.12</td>" in text
    assert "commanded_mm" not in text and "AP_mm" not in text
    assert "<dt>AP</dt>" in text and "<dt>RP</dt>" in text  # glossary of the symbols used
    assert Path(out / "path_3d.png").is_file()  # figures outside out_dir are copied in


def test_intervals_render_in_both_shapes():
    """A characteristic's 95 % interval as a sibling ``KEY_ci95`` or in a ``ci95`` block."""
    iso = {
        "poses": {
            "P1": {"n_cycles": 30, "AP_mm": 0.5, "AP_mm_ci95": [0.4, 0.6], "RP_mm": 0.1},
            "P2": {"n_cycles": 30, "AP_mm": 0.7, "RP_mm": 0.2, "ci95": {"RP_mm": [0.15, 0.3]}},
        }
    }
    (table,) = iso_tables(iso)
    assert table.columns == ["characteristic", "P1", "P2"]
    rows = {r[0]: r[1:] for r in table.rows}
    assert set(rows) == {"cycles n", "position accuracy AP [mm]", "position repeatability RP [mm]"}
    ap, rp = rows["position accuracy AP [mm]"], rows["position repeatability RP [mm]"]
    assert ap[0] == Value(0.5, (0.4, 0.6)) and ap[1] == Value(0.7, None)
    assert rp[0] == Value(0.1, None) and rp[1] == Value(0.2, (0.15, 0.3))
    assert interval_of({"x": 1.0, "x_ci95": [float("nan"), 2.0]}, "x") is None
    assert _cell(Value(0.5, (0.4, 0.6))) == '0.5 <span class="ci">[0.4, 0.6]</span>'
    assert _cell(Value(None, (0.4, 0.6))) == "–" and _cell(float("nan")) == "–"


def test_wide_blocks_are_split_into_tables_of_six_columns():
    iso = {"paths": {f"T{i}->T{i + 1}": {"AT_mm": 0.1 * i} for i in range(14)}}
    tables = iso_tables(iso)
    assert [len(t.columns) - 1 for t in tables] == [6, 6, 2]
    assert [c for t in tables for c in t.columns[1:]] == list(iso["paths"])


def test_column_labels_carry_words_and_units():
    assert column_label("t_stab_mean_s") == "stabilisation time t_stab, mean [s]"
    assert column_label("FV_mm_per_s") == "velocity fluctuation FV [mm/s]"
    assert column_label("AV_percent") == "velocity accuracy AV [%]"
    assert column_label("RPb_deg") == "orientation repeatability RP, b (about y) [°]"
    assert column_label("new_thing_mm") == "new_thing [mm]"  # unknown: key and unit


def test_robust_limit_is_median_plus_ten_mad_sigmas():
    rng = np.random.default_rng(1)
    v = np.abs(rng.normal(100.0, 10.0, 5000))
    v[::100] = 2e4  # 1 % spikes, far above the normal level
    top, n = robust_limit(np.concatenate([v, [np.nan]]))
    med = np.median(v)
    want = med + 10 * 1.4826 * np.median(np.abs(v - med))
    assert top == pytest.approx(want) and n == 50
    # the scale follows the bulk: within 10 % of the Gaussian σ of the clean part (σ = 10)
    assert top == pytest.approx(100.0 + 10 * 10.0, rel=0.1)


def _calibration(estimated, effects, names, sigma, dropped=()):
    from robtraj.estimate._calib_result import CalibrationResult
    from robtraj.recording import Pose

    pose = Pose(np.array([0.1, 0.2, 0.3]), np.array([1.0, 0.0, 0.0, 0.0]))
    return CalibrationResult(
        camera_from_base=pose, flange_from_tool=pose, led_ids=np.arange(3),
        constellation=np.zeros((3, 3)), effects=effects, estimated=tuple(estimated),
        parameter_names=tuple(names), covariance=np.diag(np.square(sigma)),
        residual_rms_m=5e-5, noise_sigma_m=3e-5, gauge="reference_constellation",
        gauge_reference=np.zeros((3, 3)),
        identifiability={"dropped": [{"parameter": p} for p in dropped]},
        iterations=4, converged=True,
    )  # fmt: skip


def test_calibration_tables_show_effects_with_sigma_and_units():
    names = ["time_offset", "joint_compliance[0]", "joint_compliance[1]", "link_length[0].d",
             "link_length[0].a"]  # fmt: skip
    c = _calibration(
        ["time_offset", "joint_compliance", "link_length"],
        {"time_offset": 2e-3, "joint_compliance": [0.0, 1.5e-6], "link_length": [[1e-5, -2e-5]]},
        names,
        [1e-5, 0.0, 2e-8, 4e-6, 5e-6],
        dropped=["joint_compliance[0]"],
    )
    cal, eff = calibration_tables(c)
    rows = {r[0]: r[1:] for r in cal.rows}
    assert rows["clock offset τ"][0] == "2.0000 (σ 0.01 ms)"
    assert rows["parameters fixed (not identifiable)"][0] == "joint_compliance[0]"
    assert rows["residual RMS of the LED positions"][0] == "50.00"
    got = {r[0]: r[1:] for r in eff.rows}
    assert list(got) == names[1:]  # τ is in the calibration table, not an effect row
    assert got["joint_compliance[0]"][0] == "fixed (not identifiable)"
    # display units: µrad/(N·m) and µm, value / σ
    assert got["joint_compliance[1]"][:3] == pytest.approx([1.5, 0.02, 75.0], rel=1e-12)
    assert got["joint_compliance[1]"][3] == "µrad/(N·m)"
    assert got["link_length[0].a"][:3] == pytest.approx([-20.0, 5.0, 4.0], rel=1e-12)
    assert got["link_length[0].a"][3] == "µm"
    none = _calibration([], {}, [], [])
    (cal,) = calibration_tables(none)
    assert {r[0]: r[1] for r in cal.rows}["clock offset τ"] == "not estimated"


def test_static_pose_errors_against_a_direct_composition():
    """Measured tool poses built as (model flange of the logged joints) · flange←tool, then
    disturbed by known flange errors: the errors come back (scipy composition and the
    model's one-pose forward kinematics as the reference)."""
    from types import SimpleNamespace

    import jax.numpy as jnp
    from scipy.spatial.transform import Rotation as R

    from robtraj.model import Effects, forward_kinematics, ur10
    from robtraj.recording import Pose, RobotLog

    rng = np.random.default_rng(3)
    n = 8
    joints = rng.uniform(-2.0, 2.0, (n, 6))
    fk = np.array([np.asarray(forward_kinematics(ur10(), jnp.asarray(q)).wxyz_xyz) for q in joints])
    r_flange, p_flange = R.from_quat(fk[:, :4], scalar_first=True), fk[:, 4:]
    ft = Pose(
        np.array([0.01, -0.02, 0.1]), R.from_rotvec([0.1, 0.2, -0.3]).as_quat(scalar_first=True)
    )
    r_ft = R.from_quat(ft.quaternion_wxyz, scalar_first=True)
    d_pos = rng.normal(0, 1e-3, (n, 3))  # flange position error [m]
    d_rot = R.from_rotvec(rng.normal(0, 1e-3, (n, 3)))  # flange orientation error
    r_meas_f = d_rot * r_flange
    bf = SimpleNamespace(
        position=p_flange + d_pos + r_meas_f.apply(ft.position),
        quaternion_wxyz=(r_meas_f * r_ft).as_quat(scalar_first=True),
        valid=np.r_[np.ones(n - 1, bool), False],
    )
    t = np.arange(n, dtype=float)
    prog = SimpleNamespace(motion=np.array(["joint"] * n, dtype="<U8"), segment=None)
    rec = SimpleNamespace(program=prog, n_frames=n, time=t,
                          robot=RobotLog(t, joints, model="ur10"))  # fmt: skip
    calib = SimpleNamespace(flange_from_tool=ft, effects_module=Effects.zeros)
    e, a = static_pose_errors(rec, calib, bf)
    np.testing.assert_allclose(e[:-1], np.linalg.norm(d_pos, axis=1)[:-1], rtol=1e-9)
    np.testing.assert_allclose(a[:-1], d_rot.magnitude()[:-1], rtol=1e-6)
    assert np.isnan(e[-1]) and np.isnan(a[-1])
    prog.motion[2] = "linear"  # a path program is not a static pose series
    assert static_pose_errors(rec, calib, bf) is None


def test_robust_limit_falls_back_to_the_largest_value_without_spread():
    v = np.array([2.0, 2.0, 2.0, 2.0, 3.5, np.nan])  # MAD 0: the limit is the largest value
    assert robust_limit(v) == (3.5, 0)
    assert robust_limit(np.zeros(4)) == (1.0, 0)
    assert np.isnan(robust_limit(np.full(3, np.nan))[0])
