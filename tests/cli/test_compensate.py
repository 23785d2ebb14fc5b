"""Close the loop on the simulator, through the CLI: a robot with hidden compliance,
link length and joint offset errors is calibrated; `compensate` corrects its ISO cube
program; the same robot runs the corrected program (`simulate --commanded`) and
`iso9283` shows what is left: exactly the cube's injected approach and drift errors,
which no model of the robot describes."""

import json

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_cli

from robtraj.sim import iso_cube_truth

DURATION, RATE = 120.0, 50.0
HIDDEN = [
    "--effect", "joint_compliance=1.5e-6",
    "--effect", "link_length=0,0,0,3e-4,0,0,0,0,0,0,0,0",
    "--effect", "joint_offset=0,0,4e-4,0,0,0",
]  # fmt: skip
#: [m] per component: AP after compensation against the injected floor. The mean of ≥ 5
#: dwells has a standard error of ≤ 3 µm (RP ≈ 40–60 µm is mostly the two approach
#: directions, S_l ≈ 2–5 µm); the calibration's TCP prediction adds a few µm. 15 µm is
#: ~3 σ of both together.
TOLERANCE = 15e-6


def _cli(*args) -> int:
    from robtraj.cli import main

    return main([str(a) for a in args])


def _iso(tmp, name, *extra):
    rec = tmp / f"{name}.h5"
    args = ["--scenario", "iso_cube", "--seed", 1, "--duration", DURATION, "--rate", RATE]
    assert _cli("simulate", rec, *args, *HIDDEN, "--no-truth", *extra) == 0
    out = tmp / f"{name}.json"
    # exit 1: characteristics a short test cannot determine (named on stderr)
    assert _cli("iso9283", rec, "--calibration", tmp / "calib.json", "--json", out) in (0, 1)
    return json.loads(out.read_text())["poses"], rec


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("compensate")
    cal, calib = tmp / "cal.h5", tmp / "calib.json"
    args = ["--scenario", "calibration", "--seed", 1, "--duration", 40, "--rate", 100]
    assert _cli("simulate", cal, *args, *HIDDEN, "--no-truth") == 0
    est = "joint_compliance,link_length,joint_offset"
    assert _cli("calibrate", cal, "-o", calib, "--estimate", est) == 0
    before, rec = _iso(tmp, "iso")
    corrected = tmp / "corrected.csv"
    assert _cli("compensate", rec, "--calibration", calib, "-o", corrected) == 0
    after, _ = _iso(tmp, "iso_compensated", "--commanded", corrected)
    return tmp, before, after


def test_compensation_leaves_only_the_unmodelled_approach_error(loop):
    _, before, after = loop
    truth = iso_cube_truth(DURATION, 1e-4)
    for name in ("P1", "P2", "P3", "P4", "P5"):
        ap = np.array([after[name][f"AP{c}_mm"] for c in "xyz"]) * 1e-3
        assert before[name]["AP_mm"] > 0.3  # the hidden effects are there
        assert np.all(np.abs(ap - truth[name]["AP_vector"]) < TOLERANCE), (name, ap)
        # repeatability is the robot's, not the program's
        assert after[name]["RP_mm"] == pytest.approx(before[name]["RP_mm"], rel=0.1, abs=2e-3)


def test_a_calibration_of_another_robot_is_refused(capsys, loop):
    tmp = loop[0]
    doc = json.loads((tmp / "calib.json").read_text())
    doc["robot"] = {"model": "ur10"}
    (tmp / "ur10.json").write_text(json.dumps(doc))
    out = tmp / "never.csv"
    code, _, err = run_cli(
        capsys, "compensate", tmp / "iso.h5", "--calibration", tmp / "ur10.json", "-o", out
    )
    assert_one_line_error(code, err, "another robot")
    assert not out.exists()
