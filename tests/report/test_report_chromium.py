"""`robtraj report` renders in headless Chromium on the demo recording, an imported
Optotrak N3D file and an imported UR10 series: no table wider than the page (from the
DOM and from the screenshot's margin), every image loaded; sections that need a program,
a robot log or a calibration are left out with a note."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _chromium import WINDOW_WIDTH, chromium, layout, screenshot
from matplotlib.image import imread

from robtraj.cli import main

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"
N3D = SHARED / "optotrak-n3d-probe" / "kinematics_sample_optotrak.n3d"
UR10 = SHARED / "ipa-robot-accuracy" / "Series_B" / "measurements_joint_configurations.csv"
CHROMIUM = chromium()
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None,
    reason="no Chromium on this machine (Debian package `chromium`, which .ci/run installs): "
    "the report's layout cannot be rendered",
)
needs_data = pytest.mark.skipif(not SHARED.is_dir(), reason="shared data not present")


def _report(args: list[str], out: Path) -> Path:
    assert main(["report", *args, "--out", str(out)]) == 0
    return out / "report.html"


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    """The demo's ISO cube run, short, reported through a calibration from another source:
    the simulation's true camera←base, flange←tool and constellation, no covariance (a
    bundle calibration costs a minute and is tested in tests/estimate)."""
    from robtraj.recording import write_recording
    from robtraj.sim import simulate

    d = tmp_path_factory.mktemp("demo")
    iso = simulate("iso_cube", seed=0, duration=30.0, rate=20.0)
    truth = iso.truth
    write_recording(iso.replace(truth=None), d / "iso_cube.h5")

    def pose(p):
        return {"position": p.position.tolist(), "quaternion_wxyz": p.quaternion_wxyz.tolist()}

    calib = {
        "camera_from_base": pose(truth.camera_from_base),
        "flange_from_tool": pose(truth.flange_from_tool),
        "constellation": {
            "led_ids": iso.tool.led_ids.tolist(),
            "positions": truth.constellation.tolist(),
        },
    }
    (d / "calibration.json").write_text(json.dumps(calib))
    return _report([str(d / "iso_cube.h5"), "--calibration", str(d / "calibration.json")], d / "r")


@pytest.fixture(scope="module")
def optotrak(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("optotrak")
    assert main(["import", str(N3D), "-o", str(d / "probe.h5"), "--preset", "optotrak-probe"]) == 0
    return _report([str(d / "probe.h5")], d / "r")


@pytest.fixture(scope="module")
def ur10(tmp_path_factory) -> Path:
    """Every 25th pose of Series B (60 static poses), imported with the preset. The bundle
    self-calibration refuses this subset ("too few distinct robot poses") after about a
    minute of compilation; the test puts a stand-in that refuses at once in its place."""
    from robtraj._errors import UserError

    d = tmp_path_factory.mktemp("ur10")
    lines = UR10.read_text().splitlines()
    (d / "series_b.csv").write_text("\n".join([lines[0], *lines[1::25]]) + "\n")
    assert main(["import", str(d / "series_b.csv"), "-o", str(d / "ur10.h5"),
                 "--preset", "ipa-ur10"]) == 0  # fmt: skip

    def refuse(rec, *a, **k):
        raise UserError("too few distinct robot poses (stand-in)")

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("robtraj.estimate.calibration.fit", refuse)
        return _report([str(d / "ur10.h5")], d / "r")


def _margin_is_blank(png: Path, right: float) -> bool:
    """No pixel right of the page (`right` px, plus 1 px of rounding) differs from white."""
    img = imread(png)[..., :3]
    assert img.shape[1] == WINDOW_WIDTH
    return bool(np.all(img[:, int(np.ceil(right)) + 1 :] > 0.98))


def check_layout(html: Path, shot: Path) -> dict:
    """Render `html`; assert every table within the page and every image loaded (DOM), and
    nothing painted in the right-hand margin (screenshot). Returns the layout facts."""
    lay = layout(html, CHROMIUM)
    page = lay["page"]
    assert lay["scrollWidth"] <= lay["innerWidth"], "the page scrolls sideways"
    for t in lay["tables"]:
        assert t["left"] >= page["left"] - 0.5 and t["right"] <= page["right"] + 0.5, t
        assert t["scrollWidth"] <= t["width"] + 1, t  # no cell content cut off
    assert lay["images"] and all(i["complete"] and i["naturalWidth"] > 0 for i in lay["images"])
    assert len(lay["images"]) == html.read_text().count("<img ")
    screenshot(html, shot, CHROMIUM, lay["height"])
    assert _margin_is_blank(shot, page["right"] + 16), "something is drawn outside the page"
    return lay


@needs_chromium
def test_layout_check_catches_a_wide_table_and_a_missing_image(tmp_path):
    """The check itself: a table wider than the page and a missing image are caught."""
    html = tmp_path / "bad.html"
    html.write_text(
        "<!DOCTYPE html><html><head><style>body{max-width:1100px;margin:2em auto;padding:0 1em}"
        "</style></head><body><table><tr><td style='white-space:nowrap'>"
        + "wide " * 400
        + "</td></tr></table><img src='missing.png'></body></html>"
    )
    lay = layout(html, CHROMIUM)
    assert lay["tables"][0]["right"] > lay["page"]["right"] + 100
    assert not lay["images"][0]["naturalWidth"]
    screenshot(html, tmp_path / "bad.png", CHROMIUM, 600)
    assert not _margin_is_blank(tmp_path / "bad.png", lay["page"]["right"] + 16)


@needs_chromium
def test_demo_report(demo):
    lay = check_layout(demo, demo.with_name("screenshot.png"))
    text = demo.read_text()
    titles = " ".join(t["title"] for t in lay["tables"])
    for want in ["Summary", "Calibration", "Pose characteristics", "Deviation summary"]:
        assert want in titles
    assert "clock offset τ</td><td>not estimated" in text  # τ was not estimated
    assert "σ" in text and "the calibration has no covariance" in text
    assert "the standard asks for 30" in text  # 3 cycles per pose in 30 s
    assert "Left out" not in text
    assert "Noise of the recording" in text  # the noise model, figure and table
    # the accuracy predicted after compensation, without σ (no covariance)
    assert "Accuracy after compensation (predicted)" in text
    assert len(lay["images"]) == 7


@needs_chromium
@needs_data
def test_optotrak_report(optotrak):
    """No robot log, no program: poses in the camera frame; the rest left out with a note."""
    lay = check_layout(optotrak, optotrak.with_name("screenshot.png"))
    text = optotrak.read_text()
    assert "no robot log" in text and "camera (tracker) frame" in text
    assert text.count("Left out:") == 3  # calibration, ISO 9283, path deviation
    assert {i["src"] for i in lay["images"]} == {
        "speed.png",
        "leds.png",
        "noise_model.png",  # the tool's rigid pairs give the noise without a robot
        "pose_quality.png",
    }


@needs_chromium
@needs_data
def test_ur10_report(ur10):
    """Static poses with a robot log and a program of joint moves: no ISO cycles and no
    linear move, said in the report, which still shows the poses and LEDs."""
    check_layout(ur10, ur10.with_name("screenshot.png"))
    text = ur10.read_text()
    assert "ur10, 6 joints" in text and "stand-in" in text
    assert "ISO 9283 and path deviation left out: no calibration" in text
    # the 4 virtual points of a 6-DOF pose carry no LED noise: no noise model to show
    assert "no LED noise of their own" in text
    assert text.count("Left out:") == 4


@needs_data
def test_report_of_marker_data_without_a_tool(tmp_path, capsys):
    """An N3D file imported without a tool: only the LED data, exit 0, notes printed."""
    assert main(["import", str(N3D), "-o", str(tmp_path / "m.h5")]) == 0
    html = _report([str(tmp_path / "m.h5")], tmp_path / "r")
    out = capsys.readouterr().out
    assert "note: no calibration: the recording has no robot log and tool constellation" in out
    text = html.read_text()
    assert "no tool constellation" in text and text.count("<img ") == 1
