"""The named model as a calibration: a pose fit written as CALIB.json predicts what the
fit predicts, through the forward model every command uses; `discrepancy
--calibration-out` then `evaluate` reproduces the workflow's cross-series figures on
the real UR10; a calibration used where it does not hold says so."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from robtraj.analysis import _pose_fit as pf, real_data as rd
from robtraj.analysis._named_model import (
    outside_maps,
    pose_calibration,
    pose_model,
    pose_representable,
)
from robtraj.analysis.prediction import predicted_tool_poses
from robtraj.calibration_file import parse_calibration
from robtraj.cli import main
from robtraj.estimate import _pose_problem as pp
from robtraj.recording import read_recording

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "cli"))
from cli_helpers import assert_one_line_error, run_cli  # noqa: E402

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "ipa-robot-accuracy"
FILES = {"A": "measurements_grid", "B": "measurements_joint_configurations"}
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="UR10 data set not present")


def _import(tmp_path, key: str, n: int) -> Path:
    """`n` evenly spaced poses of series `key` imported by `robtraj import`."""
    lines = (DATA / f"Series_{key}" / f"{FILES[key]}.csv").read_text().splitlines(keepends=True)
    keep = np.linspace(0, len(lines) - 2, n).round().astype(int) + 1
    src = tmp_path / f"{key}.csv"
    src.write_text("".join([lines[0], *(lines[i] for i in keep)]))
    out = tmp_path / f"{key}.h5"
    assert main(["import", str(src), "-o", str(out), "--preset", "ipa-ur10"]) == 0
    return out


def test_a_pose_fit_as_calibration_predicts_what_the_fit_predicts(tmp_path):
    """Series B (300 poses, with temperature): a fit with maps, per-joint compliance and
    thermal drift, written as CALIB.json and read back, predicts every probe pose through
    `predict_tool_poses` (the forward model of evaluate, iso9283, deviation, report) as
    the pose fit does, to 1e-9 m and 1e-9 rad; read back into the pose layout it is the
    same θ."""
    path = _import(tmp_path, "B", 300)
    rec = read_recording(path)
    series = rd.series_from_recording(rec, "B")
    named = ("joint_offset", "link_length", "joint2_map", "joint_compliance[1,2]", "thermal_drift")
    fit = pf.fit_poses(series, estimate=named)
    assert fit.converged and np.any(fit.theta[pp.pose_slices()["thermal_drift"]] != 0)
    calib = pose_calibration(fit, rec, series, named=named, noise_m=18e-6, source=str(path))
    doc = json.loads(json.dumps(calib.to_json()).replace("NaN", "null"))
    back = parse_calibration(doc)
    assert back.maps["joint2_map"]["estimated"] == calib.maps["joint2_map"]["estimated"]
    assert back.provenance["named"] == list(named) and pose_representable(back)
    pred = predicted_tool_poses(rec, back, np.asarray(rec.probe.time, float))
    pos, ang = pf.pose_errors(np.asarray(pred.wxyz_xyz), fit.predict(series))
    assert pos.max() < 1e-9 and ang.max() < 1e-9
    model = pose_model(back, series)
    expected = fit.theta.copy()
    expected[:12] = 0.0  # the rigid transforms are the model's start
    np.testing.assert_allclose(model.theta, expected, rtol=0, atol=1e-15)
    # the σ quoted are those of the fit
    sig = back.sigma
    for name, (_, s) in fit.parameters().items():
        assert sig[name] == pytest.approx(s, rel=1e-12)


def test_named_model_from_the_command_line_reproduces_the_workflow(tmp_path, capsys):
    """500 poses per series, CLI only: `discrepancy A --validate-on B --calibration-out
    NAMED_A.json`, then `evaluate B --calibration NAMED_A.json --refit camera,probe` gives
    the workflow's own A→B figures (same effects named as on all poses, docs/real_ur10.md);
    what it prints is what it writes; the file reads back with its schema version;
    another schema version, a recording of another robot, and an LED recording to
    validate on are one-line errors."""
    a, b = _import(tmp_path, "A", 500), _import(tmp_path, "B", 500)
    named, wf_json, figs = tmp_path / "NAMED_A.json", tmp_path / "wf.json", tmp_path / "figs"
    code, out, _ = run_cli(
        capsys, "discrepancy", a, "--validate-on", b, "--calibration-out", named,
        "--json", wf_json, "--report", figs,
    )  # fmt: skip
    assert code == 0 and f"written to {named}" in out
    wf = json.loads(wf_json.read_text())
    # what it prints is what it writes, with the maps in words and their figure
    assert "| model |" in out and "cross-validation" in wf["naming"]
    for step in wf["steps"]:
        assert f"+ {step['effect']} (round {step['round']})" in out
        for line in step.get("term", {}).get("words", []):
            assert line in out
    for r in wf["rejected"]:
        assert f"not named: {r['effect']}" in out
    assert len(wf["candidates"]) >= len(rd.CANDIDATES)
    for key, names in wf["named"].items():
        if "joint_map" in names:
            assert (figs / f"joint_maps_{key}.png").is_file()
    library = ["joint_map", "link_twist", "link_length", "joint_compliance[1,2]", "joint_offset"]
    assert wf["named"]["A"] == library
    doc = json.loads(named.read_text())
    assert doc["schema_version"] == 2 and doc["provenance"]["named"] == library
    assert set(doc["maps"]) <= {f"joint{j}_map" for j in range(1, 7)} and doc["maps"]
    cross = [r for r in wf["table"] if r["column"] == "A->B"]
    final = [r for r in cross if r["model"] == "+ joint_offset (named on A)"][0]

    ev = tmp_path / "ev.json"
    code, out, err = run_cli(
        capsys, "evaluate", b, "--calibration", named, "--refit", "camera,probe", "--json", ev
    )
    result = json.loads(ev.read_text())
    got = result["summary"]
    assert code == 0
    # B reaches angles where A's maps were not fitted: said on stderr and in the JSON
    warned = result["warnings"]
    assert warned and all(w["kind"] == "joint_map_outside_fitted_range" for w in warned)
    for w in warned:
        assert f"joint {w['joint']} in {100 * w['fraction']:.1f} % of the poses" in err
    assert got["pos_mean_mm"] == pytest.approx(final["pos_mean_mm"], rel=1e-6)
    assert got["ang_mean_deg"] == pytest.approx(final["ang_mean_deg"], rel=1e-6)

    future = tmp_path / "future.json"
    future.write_text(json.dumps({**doc, "schema_version": 3}))
    code, _, err = run_cli(capsys, "evaluate", b, "--calibration", future)
    assert_one_line_error(code, err, "schema_version 3")

    from robtraj import write_recording
    from robtraj.sim import simulate

    other = tmp_path / "other.h5"
    write_recording(simulate("paper", duration=2.0, rate=50.0), other)
    code, _, err = run_cli(capsys, "evaluate", other, "--calibration", named)
    assert_one_line_error(code, err, "calibrated robot 'ur10'")
    # an LED recording has no poses to validate on
    code, _, err = run_cli(capsys, "discrepancy", a, "--validate-on", other)
    assert_one_line_error(code, err, "pose recordings")


def test_joints_outside_a_maps_fitted_range_are_counted():
    """A map estimated on knots 10–20 only: angles between them are inside, an angle
    whose lower or upper knot is held is outside; the share is that of the rows."""
    est = np.zeros(256, bool)
    est[10:21] = True
    h = 2 * np.pi / 256
    identity = {"position": [0.0, 0.0, 0.0], "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]}
    calib = parse_calibration(
        {
            "camera_from_base": identity,
            "flange_from_tool": identity,
            "constellation": {"led_ids": [0, 1, 2], "positions": np.eye(3).tolist()},
            "effects": {"joint3_map": np.zeros(256).tolist()},
            "maps": {"joint3_map": {"estimated": est.tolist()}},
        }
    )
    q = np.zeros((4, 6))
    q[:, 2] = [10.5 * h, 19.9 * h, 20.5 * h, 3.0]
    out = outside_maps(calib, q)
    assert [(w["joint"], w["fraction"]) for w in out] == [(3, 0.5)]
    assert outside_maps(calib, q[:2]) == []
