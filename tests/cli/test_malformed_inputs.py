"""Malformed CALIB.json and recordings thrown at every command that reads them: exit 2, one
line ``robtraj: error: …``, no traceback, the input file unchanged."""

from __future__ import annotations

import copy
import json

import h5py
import numpy as np
import pytest
from cli_helpers import assert_one_line_error, digest, run_cli, valid_calibration, write_small
from hypothesis import HealthCheck, given, settings, strategies as st

from robtraj.calibration_file import load_calibration, parse_calibration

SETTINGS = settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

# ----------------------------------------------------------------------------- CALIB.json

_not_number = st.one_of(
    st.none(), st.text(max_size=4), st.dictionaries(st.text(max_size=2), st.integers(), max_size=2)
)
_bad_float = st.sampled_from([float("nan"), float("inf"), -float("inf")])


def _bad_vector(n: int):
    """Lists that are never a finite vector of `n` numbers."""
    wrong_length = (
        st.integers(0, 6)
        .filter(lambda k: k != n)
        .flatmap(lambda k: st.lists(st.floats(-10, 10), min_size=k, max_size=k))
    )
    non_finite = st.tuples(
        st.lists(st.floats(-10, 10), min_size=n - 1, max_size=n - 1), _bad_float
    ).map(lambda t: [*t[0], t[1]])
    not_numbers = st.lists(_not_number, min_size=n, max_size=n)
    return st.one_of(wrong_length, non_finite, not_numbers, _not_number)


def _bad_quaternion():
    zero = st.just([0.0, 0.0, 0.0, 0.0])
    # norm off 1 by more than the loader's 1e-3 tolerance
    off_norm = (
        st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1))
        .filter(lambda q: abs(float(np.linalg.norm(q)) - 1.0) > 1e-2)
        .map(list)
    )
    return st.one_of(zero, off_norm, _bad_vector(4))


def _mutations():
    """(description, function doc -> None) pairs that each make a CALIB.json invalid."""
    pose_key = st.sampled_from(["camera_from_base", "flange_from_tool"])

    def setter(path, value):
        def apply(doc):
            d = doc
            for k in path[:-1]:
                d = d[k]
            d[path[-1]] = value

        return apply

    def dropper(path):
        def apply(doc):
            d = doc
            for k in path[:-1]:
                d = d[k]
            del d[path[-1]]

        return apply

    required = st.sampled_from(
        [
            ("camera_from_base",),
            ("flange_from_tool",),
            ("constellation",),
            ("camera_from_base", "position"),
            ("flange_from_tool", "quaternion_wxyz"),
            ("constellation", "led_ids"),
            ("constellation", "positions"),
        ]
    )
    return st.one_of(
        required.map(lambda p: (f"missing {'.'.join(p)}", dropper(p))),
        st.tuples(pose_key, _bad_vector(3)).map(
            lambda t: (f"{t[0]}.position={t[1]!r}", setter((t[0], "position"), t[1]))
        ),
        st.tuples(pose_key, _bad_quaternion()).map(
            lambda t: (f"{t[0]}.quaternion={t[1]!r}", setter((t[0], "quaternion_wxyz"), t[1]))
        ),
        st.tuples(pose_key, _not_number).map(lambda t: (f"{t[0]}={t[1]!r}", setter((t[0],), t[1]))),
        st.sampled_from([[0, 0, 1, 2], [0, 1], [-1, 0, 1, 2], [0.5, 1, 2, 3]]).map(
            lambda ids: (f"led_ids={ids}", setter(("constellation", "led_ids"), ids))
        ),
        _bad_vector(3).map(
            lambda v: (f"positions row {v!r}", setter(("constellation", "positions", 0), v))
        ),
        st.one_of(
            st.just({"parameters": ["a", "b"], "matrix": [[1.0, 0.0]]}),
            st.just({"parameters": ["a"], "matrix": [[float("nan")]]}),
            st.just([[1.0]]),
            st.just("none"),
        ).map(lambda c: (f"covariance={c!r}", setter(("covariance",), c))),
        st.one_of(_bad_float, st.text(max_size=3), st.just(-1.0)).map(
            lambda v: (f"residual_rms_m={v!r}", setter(("residual_rms_m",), v))
        ),
        st.just(("unknown effect", setter(("effects",), {"gravity_waves": 1.0}))),
        st.one_of(
            st.just([]), st.just("none"), st.just({"undetermined": "camera_from_base.tx"})
        ).map(lambda v: (f"identifiability={v!r}", setter(("identifiability",), v))),
    )


def _bad_file():
    """Whole-file defects: not JSON, not an object, binary, an HDF5 file."""
    return st.one_of(
        st.binary(min_size=1, max_size=40).map(lambda b: ("binary", b"\xff\xfe" + b)),
        st.just(("hdf5 magic", b"\x89HDF\r\n\x1a\n" + bytes(40))),
        st.just(("empty", b"")),
        st.text(max_size=20).map(
            lambda t: ("truncated JSON", ('{"camera_from_base": ' + t).encode())
        ),
        st.one_of(
            st.lists(st.integers(), max_size=3), st.integers(), st.none(), st.text(max_size=5)
        ).map(lambda v: (f"top level {v!r}", json.dumps(v).encode())),
    )


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return write_small(tmp_path_factory.mktemp("rec") / "rec.h5")


@SETTINGS
@given(
    case=st.one_of(
        _mutations().map(lambda m: ("mutation", m)), _bad_file().map(lambda f: ("file", f))
    )
)
def test_malformed_calibration_is_one_line_exit_2_for_every_command(
    tmp_path, capsys, recording, case
):
    kind, (what, change) = case
    calib = tmp_path / "calib.json"
    if kind == "mutation":
        doc = copy.deepcopy(valid_calibration())
        change(doc)
        calib.write_text(json.dumps(doc))
    else:
        calib.write_bytes(change)
    before = digest(calib), digest(recording)
    for cmd in (["iso9283"], ["deviation"], ["report", "--out", tmp_path / "r"]):
        code, out, err = run_cli(
            capsys, *cmd, recording, "--calibration", calib, "--json", tmp_path / "o.json"
        )
        assert_one_line_error(code, err, str(calib))
        assert (digest(calib), digest(recording)) == before, what
        assert not (tmp_path / "o.json").exists() and not (tmp_path / "r").exists()


def test_the_valid_calibration_is_accepted_with_null_covariance(tmp_path):
    doc = valid_calibration()
    path = tmp_path / "c.json"
    path.write_text(json.dumps(doc))
    c = load_calibration(path)
    assert c.covariance.shape == (0, 0) and c.sigma == {}
    np.testing.assert_array_equal(c.camera_from_base.position, [0.1, 1.0, 3.0])
    # a quaternion off unit norm by rounding only is normalised
    doc["flange_from_tool"]["quaternion_wxyz"] = [0, 1.0 + 1e-5, 0, 0]
    q = parse_calibration(doc).flange_from_tool.quaternion_wxyz
    np.testing.assert_allclose(q, [0, 1, 0, 0], atol=1e-15)


# ----------------------------------------------------------------------------- recordings


def _break_h5(kind: str, path, rng):
    with h5py.File(path, "r+") as f:
        if kind == "positions shape":
            del f["tracker/positions"]
            f["tracker/positions"] = np.zeros((50, 3, 3))
        elif kind == "time decreasing":
            t = f["tracker/time"][...]
            f["tracker/time"][...] = t[::-1]
        elif kind == "time NaN":
            t = f["tracker/time"][...]
            t[int(rng.integers(0, t.size))] = np.nan
            f["tracker/time"][...] = t
        elif kind == "no positions":
            del f["tracker/positions"]
        elif kind == "frame_index short":
            del f["tracker/frame_index"]
            f["tracker/frame_index"] = np.arange(10, dtype=np.uint64)
        elif kind == "schema":
            f.attrs["schema"] = "something-else"
        elif kind == "schema_version":
            f.attrs["schema_version"] = 99
        elif kind == "led_ids text":
            del f["tracker/led_ids"]
            f["tracker/led_ids"] = np.array([b"a", b"b", b"c", b"d"])
        elif kind == "no tracker":
            del f["tracker"]


_H5_DEFECTS = [
    "positions shape",
    "time decreasing",
    "time NaN",
    "no positions",
    "frame_index short",
    "schema",
    "schema_version",
    "led_ids text",
    "no tracker",
]


@SETTINGS
@given(
    case=st.one_of(
        st.sampled_from(_H5_DEFECTS).map(lambda k: ("h5", k)),
        st.binary(max_size=64).map(lambda b: ("bytes", b)),
        st.just(("hdf5 without schema", None)),
    ),
    seed=st.integers(0, 2**16),
)
def test_malformed_recording_is_one_line_exit_2_for_every_command(
    tmp_path_factory, capsys, case, seed
):
    kind, detail = case
    tmp_path = tmp_path_factory.mktemp("example")  # hypothesis reuses a function's tmp_path
    rec = tmp_path / "rec.h5"
    if kind == "h5":
        write_small(rec)
        _break_h5(detail, rec, np.random.default_rng(seed))
    elif kind == "bytes":
        rec.write_bytes(detail)
    else:
        with h5py.File(rec, "w") as f:
            f["x"] = np.arange(3)
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps(valid_calibration()))
    before = digest(rec), digest(calib)
    o = tmp_path / "o"
    commands = [
        ["poses", rec, "-o", o / "p.h5"],
        ["calibrate", rec, "-o", o / "c.json"],
        ["iso9283", rec, "--calibration", calib, "--json", o / "i.json"],
        ["deviation", rec, "--calibration", calib, "--json", o / "d.json"],
        ["report", rec, "--calibration", calib, "--out", o / "r"],
        ["discrepancy", rec, "--json", o / "x.json"],
        ["emulate", rec, "--port", "socket://127.0.0.1:0", "--client-timeout", "0.01"],
        ["import", rec, "--format", "n3d", "-o", o / "n.h5"],
        ["import", rec, "--format", "natnet", "-o", o / "t.h5"],
    ]
    o.mkdir()
    for cmd in commands:
        code, out, err = run_cli(capsys, *cmd)
        assert_one_line_error(code, err)
        assert (digest(rec), digest(calib)) == before, (kind, detail, cmd[0])
        assert not any(o.iterdir()), cmd[0]
