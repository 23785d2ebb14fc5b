"""NDI Optotrak N3D importer against the real files in shared/data/optotrak-n3d-probe."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robtraj import RecordingError, UserError, read_recording, write_recording
from robtraj.importers import BUILTIN_CONSTELLATIONS, import_file, import_n3d, load_constellation
from robtraj.importers._n3d import read_n3d

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "optotrak-n3d-probe"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="shared data not present")

# file -> (frames, collection time, collection date) from the README / headers
FILES = {
    "kinematics_racing_probing_acromion_R.n3d": (140, "14:30:22", "03/06/17"),
    "kinematics_racing_probing_medial_epicondyle_R.n3d": (140, "14:29:26", "03/06/17"),
    "kinematics_racing_probing_olecrane_R.n3d": (140, "14:29:06", "03/06/17"),
    "kinematics_racing_probing_radial_styloid_R.n3d": (140, "14:28:33", "03/06/17"),
    "kinematics_racing_probing_ulnar_styloid_R.n3d": (140, "14:28:46", "03/06/17"),
    "kinematics_racing_static.n3d": (700, "14:39:34", "03/06/17"),
    "kinematics_sample_optotrak.n3d": (140, "15:31:31", "02/06/17"),
}
# README "checks we ran": median / max per-frame RMS of a rigid probe fit [mm]
FIT_RMS = {
    "kinematics_racing_probing_acromion_R.n3d": (0.141, 0.185),
    "kinematics_racing_probing_medial_epicondyle_R.n3d": (0.070, 0.098),
    "kinematics_racing_probing_olecrane_R.n3d": (0.184, 0.245),
    "kinematics_racing_probing_radial_styloid_R.n3d": (0.158, 0.201),
    "kinematics_racing_probing_ulnar_styloid_R.n3d": (0.138, 0.176),
    "kinematics_sample_optotrak.n3d": (0.041, 0.075),
}


def _kabsch_rms(model: np.ndarray, seen: np.ndarray) -> float:
    a, b = model - model.mean(0), seen - seen.mean(0)
    u, _, vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(u @ vt))
    rot = u @ np.diag([1.0, 1.0, d]) @ vt
    return float(np.sqrt(np.mean(np.sum((a @ rot.T - b) ** 2, axis=1))))


@pytest.mark.parametrize("name", sorted(FILES))
def test_header_and_layout(name):
    frames, hhmmss, date = FILES[name]
    header, mm = read_n3d(DATA / name)
    assert (header.file_type, header.n_markers, header.n_dims) == (32, 41, 3)
    assert header.n_frames == frames and header.frame_rate == 70.0
    assert header.system_comment == "Data File"
    assert header.collection_time == hhmmss and header.collection_date == date
    assert mm.shape == (frames, 41, 3)

    rec = import_n3d(DATA / name, constellation="optotrak-probe")
    assert rec.attrs["source"] == "import" and rec.robot is None and rec.program is None
    np.testing.assert_array_equal(rec.led_ids, np.arange(41))  # NDI's 0-based markers
    np.testing.assert_allclose(rec.time, np.arange(frames) / 70.0)
    np.testing.assert_allclose(rec.positions, mm * 1e-3, equal_nan=True)
    np.testing.assert_array_equal(rec.status == 1, ~rec.visible)
    assert np.nanmax(np.abs(rec.positions)) < 5.0  # metres, no sentinel left


def test_sample_values_match_toolkit_regression():
    # kineticstoolkit: sum over frames of (x, y, z, 1) in metres
    rec = import_n3d(DATA / "kinematics_sample_optotrak.n3d")
    p = rec.positions
    assert np.all(np.isfinite(p[:, [0, 40]]))
    assert np.sum(p[:, 0]) + 140 == pytest.approx(172.3365, abs=1e-4)
    assert np.sum(p[:, 40]) + 140 == pytest.approx(-45.3753, abs=1e-4)
    vis = rec.visible[:, :6].sum(axis=1)
    assert vis.min() >= 4 and vis.max() <= 5
    assert 0.2 < 1 - rec.visible.mean() < 0.3  # "~25 % of all samples missing"


def test_missing_markers_as_readme_says():
    vis = {n: import_n3d(DATA / n).visible for n in FILES}
    assert (~vis["kinematics_racing_probing_acromion_R.n3d"][:, 1]).sum() == 2
    assert not vis["kinematics_racing_probing_olecrane_R.n3d"][:, 7].any()
    assert (~vis["kinematics_racing_probing_radial_styloid_R.n3d"][:, :6]).sum() == 1
    assert vis["kinematics_racing_probing_medial_epicondyle_R.n3d"][:, :6].all()
    assert vis["kinematics_racing_probing_ulnar_styloid_R.n3d"][:, :6].all()
    assert not vis["kinematics_racing_static.n3d"][:, :6].any()


@pytest.mark.parametrize("name", sorted(FIT_RMS))
def test_probe_preset_fits_real_markers(name):
    rec = import_n3d(DATA / name, constellation="optotrak-probe")
    tool = rec.tool
    cols = [int(np.flatnonzero(rec.led_ids == i)[0]) for i in tool.led_ids]
    rms = []
    for frame in rec.positions[:, cols]:
        ok = np.all(np.isfinite(frame), axis=1)
        rms.append(_kabsch_rms(tool.constellation[ok], frame[ok]) * 1e3)
    median, worst = FIT_RMS[name]
    assert np.median(rms) == pytest.approx(median, abs=2e-3)
    assert np.max(rms) == pytest.approx(worst, abs=2e-3)


def test_round_trip_and_dispatch(tmp_path):
    src = DATA / "kinematics_racing_probing_acromion_R.n3d"
    rec = import_file(src, preset="optotrak-probe")
    assert rec.tool is not None and list(rec.tool.reference_leds) == [0, 1, 3]
    out = write_recording(rec, tmp_path / "a.h5")
    back = read_recording(out)
    assert back.attrs["source"] == "import" and back.attrs["n3d_collection_time"] == "14:30:22"
    np.testing.assert_array_equal(back.positions, rec.positions)
    np.testing.assert_array_equal(back.tool.constellation, rec.tool.constellation)
    rate = import_n3d(src, rate=100.0)
    assert rate.time[-1] == pytest.approx(1.39)


def test_truncated_and_corrupted_files(tmp_path):
    data = (DATA / "kinematics_sample_optotrak.n3d").read_bytes()
    short = tmp_path / "short.n3d"
    short.write_bytes(data[:-100])
    with pytest.raises(RecordingError, match="truncated.*140 frames"):
        import_n3d(short)
    tiny = tmp_path / "tiny.n3d"
    tiny.write_bytes(data[:100])
    with pytest.raises(RecordingError, match="shorter than the 256-byte"):
        import_n3d(tiny)
    bad_type = tmp_path / "type.n3d"
    bad_type.write_bytes(b"\x07" + data[1:])
    with pytest.raises(RecordingError, match="file type byte is 7"):
        import_n3d(bad_type)
    bad_dims = tmp_path / "dims.n3d"
    bad_dims.write_bytes(data[:3] + b"\x05\x00" + data[5:])
    with pytest.raises(RecordingError, match="corrupted N3D header"):
        import_n3d(bad_dims)
    long = tmp_path / "long.n3d"
    long.write_bytes(data + b"\0" * 12)
    with pytest.raises(RecordingError, match="longer than its header says"):
        import_n3d(long)


def test_constellation_files(tmp_path):
    probe = BUILTIN_CONSTELLATIONS["optotrak-probe"]
    js = tmp_path / "c.json"
    js.write_text(
        '{"led_ids": [0, 1, 2], "positions": [[0, 0, 0], [10, 0, 0], [0, 10, 0]], "unit": "mm",'
        ' "reference_leds": [0, 1, 2]}'
    )
    tool = load_constellation(js)
    np.testing.assert_allclose(tool.constellation[1], [0.01, 0, 0])
    csv = tmp_path / "c.csv"
    csv.write_text(
        "id,x,y,z\n"
        + "".join(f"{i},{x},{y},{z}\n" for i, (x, y, z) in enumerate(probe.constellation))
    )
    np.testing.assert_allclose(load_constellation(csv).constellation, probe.constellation)
    rec = import_n3d(DATA / "kinematics_sample_optotrak.n3d", constellation=csv)
    np.testing.assert_array_equal(rec.tool.led_ids, np.arange(6))
    with pytest.raises(UserError, match="no such constellation"):
        load_constellation(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"led_ids": [50, 51, 52], "positions": [[0,0,0],[1,0,0],[0,1,0]]}')
    with pytest.raises(RecordingError, match=r"constellation LEDs \[50, 51, 52\]"):
        import_n3d(DATA / "kinematics_sample_optotrak.n3d", constellation=bad)
