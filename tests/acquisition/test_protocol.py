"""The robtraj stream protocol: CRC, worked example, decoder properties, protocol registry."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from acquisition import protocol as proto
from acquisition.events import EndOfStream, LedFrame, LedFrames, StatusMessage
from acquisition.protocols import make_decoder, names
from robtraj import UserError

PROTOCOL_MD = Path(proto.__file__).with_name("PROTOCOL.md")


def test_crc_check_value():
    assert proto.crc16(b"123456789") == 0x29B1
    assert proto.crc16(b"") == 0xFFFF


def _crc_bitwise(data: bytes) -> int:
    crc = 0xFFFF
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


@given(st.binary(max_size=64))
def test_crc_matches_bitwise_definition(data):
    assert proto.crc16(data) == _crc_bitwise(data)


def _example_frame() -> bytes:
    pos = np.array([[100.5, -20.25, 2500.0], [np.nan] * 3], np.float32)
    return proto.encode_led_frame(0xFFFFFFFF, 1_234_567, np.array([7, 12]), pos, np.array([0, 1]))


def test_worked_example_in_protocol_md():
    text = PROTOCOL_MD.read_text()
    block = re.search(r"<!-- example-frame -->\s*```\s*\n(.*?)\n```", text, re.S).group(1)
    wire = _example_frame()
    assert bytes.fromhex(block.replace(" ", "")) == wire
    assert f"0x{proto.crc16(wire[:4]):04X}" == "0xC1E9" and "0xC1E9" in text
    assert f"0x{proto.crc16(wire[6:-2]):04X}" == "0x939E" and "0x939E" in text
    status = proto.encode_status(1_234_567, 24.5)
    assert " ".join(f"{b:02x}" for b in status) in " ".join(text.split())
    assert proto.encode_end_of_stream().hex(" ") in text
    (ev,) = proto.Decoder().feed(wire)
    assert ev.frame_counter == 0xFFFFFFFF and ev.device_time == 1.234567
    np.testing.assert_array_equal(ev.led_ids, [7, 12])
    np.testing.assert_array_equal(ev.positions[0], np.array([100.5, -20.25, 2500.0]) / 1000)
    assert np.all(np.isnan(ev.positions[1])) and list(ev.status) == [0, 1]


def test_missing_status_means_nan_even_with_coordinates():
    wire = proto.encode_led_frame(
        1, 10, np.array([1, 2]), np.ones((2, 3), np.float32), np.array([1, 3])
    )
    (ev,) = proto.Decoder().feed(wire)
    assert np.all(np.isnan(ev.positions[0]))
    np.testing.assert_array_equal(ev.positions[1], [1e-3] * 3)


def test_bad_length_and_unknown_type_are_counted():
    d = proto.Decoder()
    good = proto.encode_status(5, 20.0)
    # valid CRCs, but an LED frame whose n does not fit L, and an unknown type
    bad_len = proto.frame(bytes([proto.TYPE_LED_FRAME]) + bytes(4 + 8) + bytes([3]) + bytes(14))
    unknown = proto.frame(bytes([0x7F, 1, 2, 3]))
    too_short = proto.frame(bytes([proto.TYPE_LED_FRAME, 0]))
    events = d.feed(bad_len + unknown + too_short + good)
    assert events == [StatusMessage(5e-6, 20.0)]
    assert d.counters["bad_length"] == 2 and d.counters["unknown_type"] == 1
    assert d.counters["resyncs"] == 1


def test_oversized_length_with_valid_header_crc():
    head = proto.SYNC + (4000).to_bytes(2, "little")
    bogus = head + proto.crc16(head).to_bytes(2, "little")
    d = proto.Decoder()
    assert d.feed(bogus + proto.encode_end_of_stream()) == [EndOfStream()]
    assert d.counters["bad_length"] == 1


def test_finish_counts_a_truncated_tail():
    wire = _example_frame()
    d = proto.Decoder()
    assert d.feed(wire + wire[:30]) != []
    assert d.finish() == []
    assert d.counters["truncated"] >= 1 and d.counters["resyncs"] == 1
    assert d.counters["bytes_skipped"] == 30


# ----------------------------------------------------------------------------- properties

finite_mm = st.floats(-5000.0, 5000.0, width=32, allow_nan=False)


@st.composite
def messages(draw) -> list[bytes]:
    """A sequence of encoded messages (LED frames with NaN for missing, status, end)."""
    out = []
    t = draw(st.integers(0, 2**40))
    for _ in range(draw(st.integers(0, 8))):
        t += draw(st.integers(1, 10**6))
        kind = draw(st.sampled_from(["frame", "frame", "frame", "status", "end"]))
        if kind == "frame":
            n = draw(st.integers(0, 5))
            ids = np.array(draw(st.lists(st.integers(0, 255), min_size=n, max_size=n)), np.uint8)
            status = np.array(draw(st.lists(st.integers(0, 3), min_size=n, max_size=n)), np.uint8)
            pos = np.array(draw(st.lists(finite_mm, min_size=3 * n, max_size=3 * n)), np.float32)
            pos = pos.reshape(n, 3)
            pos[status == 1] = np.nan
            counter = draw(st.integers(0, 2**32 - 1))
            out.append(proto.encode_led_frame(counter, t, ids, pos, status))
        elif kind == "status":
            temp = draw(st.floats(-40, 90, width=32))
            out.append(proto.encode_status(t, temp))
        else:
            out.append(proto.encode_end_of_stream())
    return out


def _split(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts})
    edges = [0, *points, len(data)]
    return [data[a:b] for a, b in zip(edges, edges[1:])]


def _decode(chunks: list[bytes], blocks: bool = False) -> tuple[list[bytes], dict]:
    """Messages decoded (re-encoded; `LedFrames` blocks as their frames) and counters."""
    d = proto.Decoder(blocks=blocks)
    events = []
    for c in chunks:
        events += d.feed(c)
    events += d.finish()
    if blocks:
        assert not any(isinstance(e, LedFrame) for e in events)
        events = [f for e in events for f in (e.frames() if isinstance(e, LedFrames) else [e])]
    return [proto.encode_event(e) for e in events], d.counters


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(messages(), st.lists(st.integers(0, 10**6), max_size=12))
def test_any_split_decodes_to_the_same_frames(msgs, cuts):
    data = b"".join(msgs)
    decoded, counters = _decode(_split(data, cuts))
    assert decoded == msgs
    assert counters["resyncs"] == counters["bytes_skipped"] == 0
    assert sum(counters[k] for k in proto.ERROR_COUNTERS) == 0


@st.composite
def damage(draw, msgs: list[bytes], keep: int = 2):
    """Damage some messages (flip bits, truncate, overwrite, insert garbage); `keep` is
    the odds of a message left alone against each kind of damage."""
    wires, touched = [], []
    for m in msgs:
        how = draw(st.sampled_from(["keep"] * keep + ["flip", "truncate", "overwrite", "garbage"]))
        if how == "keep":
            wires.append(m)
            touched.append(False)
        elif how == "garbage":  # junk before an intact message: nothing lost
            wires.append(draw(st.binary(min_size=1, max_size=40)) + m)
            touched.append(False)
        elif how == "truncate":
            wires.append(m[: draw(st.integers(0, len(m) - 1))])
            touched.append(True)
        elif how == "flip":
            b = bytearray(m)
            for bit in draw(
                st.lists(st.integers(0, 8 * len(m) - 1), min_size=1, max_size=3, unique=True)
            ):
                b[bit // 8] ^= 1 << (bit % 8)
            wires.append(bytes(b))
            touched.append(True)
        else:
            b = bytearray(m)
            start = draw(st.integers(0, len(m) - 1))
            junk = draw(st.binary(min_size=1, max_size=20))
            b[start : start + len(junk)] = junk
            w = bytes(b[: len(m)])
            wires.append(w)
            touched.append(w != m)
    return wires, touched


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_corruption_never_invents_and_loses_only_what_it_touched(data):
    msgs = data.draw(messages())
    wires, touched = data.draw(damage(msgs))
    stream = b"".join(wires)
    cuts = data.draw(st.lists(st.integers(0, 10**6), max_size=8))
    decoded, counters = _decode(_split(stream, cuts))
    untouched = [m for m, t in zip(msgs, touched) if not t]
    # nothing invented: every decoded message was sent, in order; nothing untouched lost
    assert decoded == untouched
    if any(touched) and any(wires):
        assert counters["bytes_skipped"] > 0 or all(not w for w, t in zip(wires, touched) if t)


@st.composite
def runs(draw) -> list[bytes]:
    """Long runs of LED frames of one size (what a device sends), now and then a status
    message or a frame of another size between them."""
    n = draw(st.integers(0, 4))
    t, counter, out = draw(st.integers(0, 2**40)), draw(st.integers(0, 2**32 - 1)), []
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    for kind in draw(st.lists(st.sampled_from(["frame"] * 12 + ["status", "other"]), max_size=60)):
        t += int(rng.integers(1, 2000))
        counter += 1
        if kind == "status":
            out.append(proto.encode_status(t, 24.5))
            continue
        k = n if kind == "frame" else (n + 1) % 5
        status = rng.integers(0, 4, k).astype(np.uint8)
        pos = np.float32(rng.normal(size=(k, 3)) * 1000.0)
        pos[status == 1] = np.nan
        out.append(proto.encode_led_frame(counter, t, np.arange(k, dtype=np.uint8), pos, status))
    return out


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_runs_checked_together_lose_only_what_was_touched_blocks_or_not(data):
    """Frames of one size are checked in vectorised runs: a damaged frame inside a run, a
    run cut by a chunk boundary or by another message, give exactly the untouched
    messages, in both output forms and with the same counters."""
    msgs = data.draw(runs())
    wires, touched = data.draw(damage(msgs, keep=data.draw(st.sampled_from([2, 40]))))
    chunks = _split(b"".join(wires), data.draw(st.lists(st.integers(0, 10**6), max_size=6)))
    untouched = [m for m, t in zip(msgs, touched) if not t]
    one_by_one, counters = _decode(chunks)
    as_blocks, block_counters = _decode(chunks, blocks=True)
    assert one_by_one == as_blocks == untouched
    assert counters == block_counters


def test_blocks_hold_consecutive_frames_of_one_size():
    ids = np.arange(3, dtype=np.uint8)
    pos = np.zeros((3, 3), np.float32)
    frames = [
        proto.encode_led_frame(i, 10 * i, ids, pos + i, np.zeros(3, np.uint8)) for i in range(9)
    ]
    other = proto.encode_led_frame(9, 90, ids[:2], pos[:2], np.zeros(2, np.uint8))
    wire = b"".join(frames[:5]) + proto.encode_status(45, 20.0) + b"".join(frames[5:]) + other
    events = proto.Decoder(blocks=True).feed(wire)
    assert [type(e) for e in events] == [LedFrames, StatusMessage, LedFrames, LedFrames]
    assert [len(e) for e in events if isinstance(e, LedFrames)] == [5, 4, 1]
    b = events[2]
    np.testing.assert_array_equal(b.frame_counter, [5, 6, 7, 8])
    np.testing.assert_array_equal(b.device_time, [50e-6, 60e-6, 70e-6, 80e-6])
    assert b.led_ids.shape == b.status.shape == (4, 3) and b.positions.shape == (4, 3, 3)
    np.testing.assert_array_equal(b.positions[:, 0, 0], np.arange(5, 9) / 1000.0)


@given(
    st.integers(1, 300).flatmap(
        lambda n: st.lists(st.binary(min_size=n, max_size=n), min_size=1, max_size=6)
    )
)
def test_crc16_rows_is_crc16_of_each_row(rows):
    got = proto.crc16_rows(np.frombuffer(b"".join(rows), np.uint8).reshape(len(rows), -1))
    assert got.tolist() == [proto.crc16(r) for r in rows]


def test_decoder_events_are_led_frames_with_the_interface_types():
    pos = np.array([[1.0, 2.0, 3.0]], np.float32)
    (ev,) = proto.Decoder().feed(proto.encode_led_frame(3, 7, np.array([9]), pos, np.array([0])))
    assert isinstance(ev, LedFrame)
    assert ev.positions.dtype == np.float64 and ev.positions.shape == (1, 3)
    assert ev.status.dtype == np.uint8 and ev.led_ids.shape == (1,)


# ----------------------------------------------------------------------------- registry


def test_registry_knows_both_protocols():
    assert {"robtraj", "natnet"} <= set(names())
    assert isinstance(make_decoder("robtraj"), proto.Decoder)


def test_registry_unknown_protocol_is_a_user_error():
    with pytest.raises(UserError, match="unknown protocol 'nope'"):
        make_decoder("nope")


def test_registry_broken_protocol_is_a_user_error(monkeypatch):
    from acquisition import protocols

    monkeypatch.setitem(protocols._REGISTRY, "broken", "acquisition.no_such_module:Decoder")
    with pytest.raises(UserError, match="protocol 'broken' is not available"):
        make_decoder("broken")


def test_natnet_decoder_has_the_interface():
    pytest.importorskip("acquisition.natnet")
    dec = make_decoder("natnet")
    assert dec.feed(b"") == [] and isinstance(dec.counters, dict)
