"""Two stories the recording cannot tell apart are said to be equally supported, with the
poses that would tell them apart; measuring those poses tells them apart.

The robot's joint 2 bends under gravity (compliance 2 µrad/(N·m) on joint 2 alone, 0.2 mm
at the tool) while it moves joint 2 over ±30° with joint 3 held: the gravity torque on
joint 2 is then a first harmonic of q2, so the compliance and a first harmonic of joint
2's angle (`joint2_harmonic1`) predict the same on this recording. The search names one
and reports the other as equally supported (Vuong's test on the held-out blocks), with
static poses chosen so that the other cannot follow them after refitting (T-optimal).
Adding the first three of them to the program (simulated, same robot) lets the search
name the compliance alone, at its true value, with nothing equally supported."""

import numpy as np
import pytest

from robtraj.analysis.discrepancy import discover
from robtraj.model import effect_component_names
from robtraj.sim import joint_dwells, simulate

COMPLIANCE = [0.0, 2e-6, 0.0, 0.0, 0.0, 0.0]  # [rad/(N·m)]
STORIES = {"joint_compliance", "joint2_harmonic1"}


def _recording(dwells: np.ndarray):
    rec = simulate("calibration", seed=1, duration=3.0 * len(dwells), rate=25.0,
                   effects={"joint_compliance": COMPLIANCE},
                   moves=joint_dwells(dwells, dwell=1.5))  # fmt: skip
    return rec.replace(truth=None)


@pytest.fixture(scope="module")
def dwells():
    """14 dwells near the calibration run's middle configuration: joint 2 over ±30°,
    joint 3 held, the base ±10° and the wrist turned."""
    base = simulate("calibration", seed=1, duration=24.0, rate=25.0)
    middle = np.median(np.asarray(base.robot.joints), axis=0)
    span = np.deg2rad([10.0, 30.0, 0.0, 40.0, 40.0, 60.0])
    return middle + np.random.default_rng(0).uniform(-1, 1, (14, 6)) * span


def test_equally_supported_stories_are_said_and_the_suggested_poses_tell_them_apart(dwells):
    res = discover(_recording(dwells))
    assert len(res.steps) == 1 and res.named[0] in STORIES, res.named
    (step,) = res.steps
    rival = (STORIES - {step.effect}).pop()
    said = {e["effect"]: e for e in step.equivalent}
    assert rival in said, (step.effect, said)
    assert said[rival]["heldout_z"] < 1.96
    poses = said[rival]["next_poses"]
    assert poses is not None and len(poses["joints_rad"]) >= 3
    assert res.to_json()["steps"][0]["equally_supported"][0]["effect"] == rival

    more = np.concatenate([dwells, np.asarray(poses["joints_rad"][:3])])
    after = discover(_recording(more))
    assert after.named == ["joint_compliance"], after.named
    assert after.steps[0].equivalent == ()
    assert after.gap_after_m <= after.gap_floor_m
    value = np.asarray(after.calibration.effects["joint_compliance"], float)
    sigma = after.calibration.sigma
    for k, name in enumerate(effect_component_names("joint_compliance", value.shape)):
        if 0 < sigma[name] < np.inf:  # joint 1 bears no gravity torque: not estimated
            assert abs(value[k] - COMPLIANCE[k]) < 3 * sigma[name], (name, value[k], sigma[name])
