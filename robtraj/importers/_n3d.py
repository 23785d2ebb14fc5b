"""NDI Optotrak N3D files (NDI "Data File", type 32): 3-D marker positions.

Layout (little-endian): a 256-byte header, then float32 samples frame-major,
marker-major, x, y, z in millimetres; NDI writes a missing marker as ``BAD_FLOAT``
(-3.697314e28), any value below -1e25 is read as missing.
"""

from __future__ import annotations

import dataclasses
import os
import struct
from pathlib import Path

import numpy as np

from ..recording import Recording, RecordingError, Tool
from ._common import load_constellation

HEADER_BYTES = 256
FILE_TYPE = 32
MISSING_BELOW = -1e25


@dataclasses.dataclass(frozen=True)
class N3DHeader:
    file_type: int
    n_markers: int
    n_dims: int
    n_frames: int
    frame_rate: float
    user_comment: str
    system_comment: str
    description: str
    cutoff_frequency: int
    collection_time: str
    collection_date: str


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1").strip()


def read_n3d_header(data: bytes, name: str = "N3D file") -> N3DHeader:
    """Decode and check the 256-byte header; `RecordingError` if it is not an N3D header."""
    if len(data) < HEADER_BYTES:
        raise RecordingError(
            f"{name}: {len(data)} bytes is shorter than the {HEADER_BYTES}-byte N3D header"
        )
    file_type = data[0]
    n_markers, n_dims, n_frames, rate = struct.unpack_from("<hhif", data, 1)
    (cutoff,) = struct.unpack_from("<h", data, 163)
    header = N3DHeader(
        file_type=file_type,
        n_markers=n_markers,
        n_dims=n_dims,
        n_frames=n_frames,
        frame_rate=float(rate),
        user_comment=_text(data[13:73]),
        system_comment=_text(data[73:133]),
        description=_text(data[133:163]),
        cutoff_frequency=cutoff,
        collection_time=_text(data[165:173]),
        collection_date=_text(data[175:183]),
    )
    if file_type != FILE_TYPE:
        raise RecordingError(f"{name}: file type byte is {file_type}, an N3D file has {FILE_TYPE}")
    if n_markers <= 0 or n_dims != 3 or n_frames < 0:
        raise RecordingError(
            f"{name}: corrupted N3D header ({n_markers} markers, {n_dims} values per marker, "
            f"{n_frames} frames)"
        )
    return header


def read_n3d(path: str | os.PathLike) -> tuple[N3DHeader, np.ndarray]:
    """The header and the raw positions `(frames, markers, 3)` [mm], NaN where missing."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise RecordingError(f"{path}: cannot read ({e.strerror or e})") from None
    header = read_n3d_header(data, str(path))
    expected = HEADER_BYTES + 4 * header.n_frames * header.n_markers * header.n_dims
    if len(data) != expected:
        what = "truncated" if len(data) < expected else "longer than its header says"
        raise RecordingError(
            f"{path}: N3D file {what}: header says {header.n_frames} frames x "
            f"{header.n_markers} markers = {expected} bytes, file has {len(data)}"
        )
    raw = np.frombuffer(data, dtype="<f4", offset=HEADER_BYTES).astype(np.float64)
    mm = raw.reshape(header.n_frames, header.n_markers, header.n_dims)
    missing = np.any(mm < MISSING_BELOW, axis=-1) | ~np.all(np.isfinite(mm), axis=-1)
    mm[missing] = np.nan
    return header, mm


def import_n3d(
    path: str | os.PathLike,
    *,
    constellation: str | os.PathLike | Tool | None = None,
    rate: float | None = None,
) -> Recording:
    """Import an NDI Optotrak N3D file as a schema-1 `Recording` (``source="import"``).

    Markers keep NDI's 0-based numbering as `led_ids` (0 .. markers-1); positions are
    converted from mm to m, missing samples become NaN (status 1). Frame ``i`` is at
    ``time = i / rate`` with the header's frame rate unless `rate` [Hz] overrides it.
    `constellation` (a built-in name such as ``"optotrak-probe"``, a JSON or CSV file,
    or a `Tool`) becomes the recording's tool.
    """
    path = Path(path)
    header, mm = read_n3d(path)
    hz = header.frame_rate if rate is None else float(rate)
    if not np.isfinite(hz) or hz <= 0:
        raise RecordingError(
            f"{path}: frame rate {hz!r} Hz is not positive; give it with --rate HZ"
        )
    n, m = header.n_frames, header.n_markers
    positions = mm * 1e-3
    tool = None
    if constellation is not None:
        tool = load_constellation(constellation)
        unknown = sorted(set(tool.led_ids.tolist()) - set(range(m)))
        if unknown:
            raise RecordingError(
                f"{path}: constellation LEDs {unknown} are not markers of this file (0..{m - 1})"
            )
    attrs = {
        "source": "import",
        "import_format": "n3d",
        "import_file": path.name,
        "n3d_frame_rate_hz": header.frame_rate,
        "n3d_collection_date": header.collection_date,
        "n3d_collection_time": header.collection_time,
        "n3d_system_comment": header.system_comment,
        "n3d_user_comment": header.user_comment,
    }
    return Recording(
        time=np.arange(n, dtype=np.float64) / hz,
        frame_index=np.arange(n, dtype=np.uint64),
        led_ids=np.arange(m, dtype=np.int32),
        positions=positions,
        status=np.where(np.isnan(positions[..., 0]), 1, 0).astype(np.uint8),
        tool=tool,
        attrs=attrs,
    )
