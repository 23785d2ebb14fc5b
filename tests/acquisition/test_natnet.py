"""NatNet 3.0 decoding against real Motive 2.1 packets and NaturalPoint's SampleClient log."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from acquisition.events import LedFrame
from acquisition.natnet import (
    NAT_FRAMEOFDATA,
    NatNetError,
    NatNetStreamDecoder,
    decode_packet,
    import_natnet,
    parse_packet,
)

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "natnet-packets"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="shared data not present")
FRAME = DATA / "mocapframe_packet_v3.bin"
OCCLUDED = DATA / "mocapframe_packet_occluded_v3.bin"


def _floats(text: str) -> list[float]:
    return [float(v) for v in re.split(r"[\s,]+", text.strip()) if v]


def parse_sample_client_log(path: Path) -> dict[int, dict]:
    """Frames of NaturalPoint's SampleClient text output, keyed by FrameID."""
    frames: dict[int, dict] = {}
    cur: dict | None = None
    lines = path.read_text().splitlines()
    for i, line in enumerate(lines):
        if m := re.match(r"FrameID : (\d+)", line):
            cur = {"other": [], "bodies": [], "labeled": []}
            frames[int(m.group(1))] = cur
        elif cur is None:
            continue
        elif m := re.match(r"Timestamp : ([\d.]+)", line):
            cur["timestamp"] = float(m.group(1))
        elif m := re.match(r"Other Marker \d+ : (.*)", line):
            cur["other"].append(_floats(m.group(1)))
        elif m := re.match(r"Rigid Body \[ID=(\d+)\s+Error=([\d.]+)\s+Valid=(\d)\]", line):
            pose = _floats(lines[i + 2])  # after the "x y z qx qy qz qw" line
            cur["bodies"].append((int(m.group(1)), float(m.group(2)), int(m.group(3)), pose))
        elif m := re.match(
            r"Labeled Marker \[ModelID=(\d+), MarkerID=(\d+), Occluded=(\d), PCSolved=(\d), "
            r"ModelSolved=(\d)\] \[size=([\d.]+)\] \[pos=(.*)\]",
            line,
        ):
            ints = [int(m.group(k)) for k in range(1, 6)]
            cur["labeled"].append((*ints, float(m.group(6)), _floats(m.group(7))))
    return frames


def test_golden_frame_matches_sample_client_log():
    log = parse_sample_client_log(DATA / "SampleClient_output.txt")
    assert len(log) == 251 and min(log) == 162734
    frame = decode_packet(FRAME.read_bytes())
    want = log[frame.frame_number]
    r2 = lambda x: np.round(np.asarray(x, np.float64), 2)  # the log prints %.2f  # noqa: E731

    assert round(frame.timestamp, 2) == want["timestamp"]
    np.testing.assert_array_equal(r2(frame.unlabeled_markers), want["other"])
    assert len(frame.rigid_bodies) == len(want["bodies"]) == 1
    for body, (rb_id, err, valid, pose) in zip(frame.rigid_bodies, want["bodies"]):
        assert (body.id, round(body.mean_error, 2), int(body.tracking_valid)) == (rb_id, err, valid)
        w, x, y, z = body.quaternion_wxyz
        np.testing.assert_array_equal(r2([*body.position, x, y, z, w]), pose)
    got = [
        (
            m.model_id,
            m.marker_id,
            int(m.occluded),
            int(m.point_cloud_solved),
            int(m.model_solved),
            round(m.size, 2),
            r2(m.position).tolist(),
        )
        for m in frame.labeled_markers
    ]
    assert got == want["labeled"]


def test_golden_frame_exact_values():
    message_id, payload = parse_packet(FRAME.read_bytes())
    assert message_id == NAT_FRAMEOFDATA and len(payload) == 332
    f = decode_packet(FRAME.read_bytes())
    assert f.frame_number == 162734 and f.marker_sets == [] and f.skeletons == []
    np.testing.assert_allclose(
        f.unlabeled_markers[0], [0.1272162, 1.5050275, -0.8858284], rtol=1e-6
    )
    rb = f.rigid_bodies[0]
    assert rb.id == 2 and rb.tracking_valid
    np.testing.assert_allclose(rb.position, [0.1744466, 1.4471314, -0.7343040], rtol=1e-6)
    np.testing.assert_allclose(
        rb.quaternion_wxyz, [-0.8573577, -0.05459423, 0.5099482, 0.04370357], rtol=1e-6
    )
    assert rb.mean_error == pytest.approx(0.0005152203, rel=1e-6)
    m0, m5 = f.labeled_markers[0], f.labeled_markers[5]
    assert (m0.model_id, m0.marker_id, m0.params) == (2, 1, 10)
    assert m0.size == pytest.approx(0.02143982, rel=1e-6)
    assert m0.residual == pytest.approx(0.0002074828, rel=1e-6)
    assert (m5.model_id, m5.marker_id, m5.params, m5.unlabeled) == (0, 50007, 18, True)
    assert f.timestamp == pytest.approx(1356.117, abs=1e-3)
    assert (f.stamp_camera_mid_exposure, f.stamp_data_received, f.stamp_transmit) == (
        1416497730518,
        1416497745808,
        1416497748722,
    )


def test_occluded_frame():
    f = decode_packet(OCCLUDED.read_bytes())
    assert f.frame_number == 269007 and f.timestamp == pytest.approx(8966.9)
    assert [(m.model_id, m.marker_id, m.params) for m in f.labeled_markers] == [
        (7, 2, 11),
        (7, 3, 10),
        (7, 4, 10),
        (7, 5, 10),
    ]
    assert [ms.name for ms in f.marker_sets] == ["FakeTree", "all"]
    assert f.rigid_bodies[0].id == 7
    (ev,) = NatNetStreamDecoder(model_id=7, led_ids=[1, 2, 3, 4, 5]).feed(OCCLUDED.read_bytes())
    assert isinstance(ev, LedFrame) and ev.frame_counter == 269007
    # marker 1 is not sent, marker 2 carries the occluded bit: both missing
    np.testing.assert_array_equal(ev.status, [1, 1, 0, 0, 0])
    assert np.isnan(ev.positions[:2]).all() and np.isfinite(ev.positions[2:]).all()


def test_bad_packets():
    data = FRAME.read_bytes()
    with pytest.raises(NatNetError, match="header says 336 bytes"):
        parse_packet(data[:-1])
    with pytest.raises(NatNetError, match="truncated"):
        decode_packet(data[:2] + (len(data) - 10).to_bytes(2, "little") + data[4:-6])
    with pytest.raises(NatNetError, match="not a frame of data"):
        decode_packet((DATA / "modeldef_packet_v3.bin").read_bytes())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stream_decoder_any_split(seed):
    names = [
        "serverinfo_packet_v3.bin",
        "mocapframe_packet_v3.bin",
        "modeldef_packet_v3.bin",
        "mocapframe_packet_occluded_v3.bin",
        "echoresponse_packet_v3.bin",
    ]
    stream = b"".join((DATA / n).read_bytes() for n in names)
    rng = np.random.default_rng(seed)
    cuts = np.sort(rng.choice(np.arange(1, len(stream)), size=40, replace=False))
    dec = NatNetStreamDecoder()
    events = []
    for chunk in np.split(np.frombuffer(stream, np.uint8), cuts):
        events += dec.feed(chunk.tobytes())
    assert [type(e) for e in events] == [LedFrame, LedFrame]
    assert dec.counters == {
        "packets": 5,
        "frames": 2,
        "other_messages": 3,
        "malformed": 0,
        "resync_bytes": 0,
    }
    first, second = events
    assert (first.frame_counter, second.frame_counter) == (162734, 269007)
    assert first.device_time == pytest.approx(1356.117, abs=1e-3)
    # wire ids (model << 16) | marker; the unlabelled marker is left out by default
    np.testing.assert_array_equal(first.led_ids, [(2 << 16) | k for k in range(1, 6)])
    np.testing.assert_allclose(first.positions[0], [0.1272162, 1.5050275, -0.8858284], rtol=1e-6)
    assert not first.status.any()
    np.testing.assert_array_equal(second.status, [1, 0, 0, 0])
    whole = NatNetStreamDecoder(model_id=2).feed(stream)
    np.testing.assert_array_equal(whole[0].led_ids, [1, 2, 3, 4, 5])
    np.testing.assert_array_equal(whole[0].positions, first.positions)


def test_import_natnet_capture(tmp_path):
    cap = tmp_path / "cap.bin"
    cap.write_bytes(FRAME.read_bytes() + OCCLUDED.read_bytes())
    rec = import_natnet(cap)
    assert rec.n_frames == 2 and rec.n_leds == 9 and rec.attrs["source"] == "import"
    np.testing.assert_array_equal(rec.frame_index, [0, 269007 - 162734])
    assert rec.visible.sum() == 5 + 3
