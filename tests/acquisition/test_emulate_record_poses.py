"""A recording sent through emulate → record gives the same poses as the original,
to the float32 precision of the wire format."""

import numpy as np
from acq_helpers import popen, wait_for_file
from test_cli_acquisition import _finish, _reap

from robtraj import read_recording, write_recording
from robtraj.estimate import estimate_poses
from robtraj.sim import simulate


def test_emulate_record_poses_equal_original(tmp_path):
    src = simulate("paper", seed=5, duration=2.5, rate=1000.0)
    write_recording(src, tmp_path / "src.h5")
    emu = popen(
        "emulate", str(tmp_path / "src.h5"), "--port", "socket://127.0.0.1:0",
        "--rate", "0", "--port-file", str(tmp_path / "port"),
    )  # fmt: skip
    try:
        url = wait_for_file(tmp_path / "port", proc=emu)
        rec = popen("record", "--port", url, "-o", str(tmp_path / "out.h5"))
        code, _, err = _finish(rec, timeout=60)
        assert code == 0, err
        assert _finish(emu)[0] == 0
    finally:
        _reap(emu)
    got = read_recording(tmp_path / "out.h5")
    assert got.n_frames == src.n_frames
    np.testing.assert_array_equal(got.led_ids, src.led_ids)
    np.testing.assert_array_equal(got.visible, src.visible)
    # float32 millimetres on the wire: |x| < 4 m → rounding ≤ 2^-24 · 4096 mm / 2 ≈ 0.12 µm
    wire = 2.0**-24 * 4.096 / 2
    np.testing.assert_allclose(got.positions, src.positions, rtol=0, atol=wire)
    const = src.tool.constellation
    a = estimate_poses(src, weighting="led_noise", constellation=const)
    b = estimate_poses(got, weighting="led_noise", constellation=const, leds=src.tool.led_ids)
    np.testing.assert_array_equal(a.valid, b.valid)
    # a pose is a weighted mean of ~10 LEDs: its error is at most the per-coordinate one,
    # amplified by the lever of the orientation (LED radius 50 mm vs the 0.1 m TCP offset)
    np.testing.assert_allclose(b.position, a.position, rtol=0, atol=5 * wire)
    dq = np.abs(np.abs(np.sum(a.quaternion_wxyz * b.quaternion_wxyz, -1)) - 1)
    assert dq.max() < (10 * wire / 0.05) ** 2
