"""The poses file written by `robtraj poses` (schema "robtraj.poses", version 1).

```
/                      attrs: schema="robtraj.poses", schema_version=1, created, recording,
                              weighting, window, constellation_source, notes (JSON)
/poses/time            (N,)    f8  tracker clock [s]
/poses/position        (N, 3)  f8  camera←tool translation [m], NaN where not valid
/poses/quaternion_wxyz (N, 4)  f8  camera←tool rotation
/poses/rms             (N,)    f8  weighted residual RMS [m]
/poses/n_used          (N,)    i4  LEDs used
/poses/valid           (N,)    u1  1 = pose computed
/constellation/led_ids (M,) i4; /constellation/positions (M, 3) f8 tool frame [m];
/constellation/uncertainty (M,) f8 [m] (registration only)
```
"""

from __future__ import annotations

import datetime
import json
import os
from pathlib import Path

import h5py
import numpy as np

from .._errors import UserError
from ._poses import PoseEstimate

SCHEMA = "robtraj.poses"


def write_poses(
    est: PoseEstimate, path: str | os.PathLike, *, recording: str = "", overwrite=False
):
    """Write `est` to a new HDF5 file (refuses to overwrite unless `overwrite`)."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise UserError(f"{path} exists; choose another name or pass --force")
    tmp = path.with_name(path.name + ".partial")
    with h5py.File(tmp, "w") as f:
        f.attrs.update(
            schema=SCHEMA,
            schema_version=1,
            created=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            recording=str(recording),
            weighting=est.weighting,
            window=est.window,
            constellation_source=est.constellation_source,
            notes=json.dumps(list(est.notes)),
        )
        g = f.create_group("poses")
        opts = dict(compression="gzip", compression_opts=1, shuffle=True)
        g.create_dataset("time", data=est.time, **opts)
        g.create_dataset("position", data=est.position, **opts)
        g.create_dataset("quaternion_wxyz", data=est.quaternion_wxyz, **opts)
        g.create_dataset("rms", data=est.rms, **opts)
        g.create_dataset("n_used", data=est.n_used.astype(np.int32), **opts)
        g.create_dataset("valid", data=est.valid.astype(np.uint8), **opts)
        c = f.create_group("constellation")
        c.create_dataset("led_ids", data=est.led_ids.astype(np.int32))
        c.create_dataset("positions", data=est.constellation)
        if est.registration is not None:
            c.create_dataset("uncertainty", data=est.registration.uncertainty)
            c.attrs["gauge"] = est.registration.gauge
            c.attrs["unreferenced"] = json.dumps(
                {str(k): v for k, v in est.registration.reasons.items()}
            )
    os.replace(tmp, path)
    return path


def read_poses(path: str | os.PathLike) -> dict:
    """Read a poses file into a dict of arrays and attributes."""
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise UserError(f"{path}: not a readable HDF5 file ({e})") from None
    with f:
        if f.attrs.get("schema") != SCHEMA:
            raise UserError(f"{path}: not a robtraj poses file (schema {f.attrs.get('schema')!r})")
        out = {k: f["poses"][k][()] for k in f["poses"]}
        out["valid"] = out["valid"].astype(bool)
        out["led_ids"] = f["constellation/led_ids"][()]
        out["constellation"] = f["constellation/positions"][()]
        out["attrs"] = {k: v for k, v in f.attrs.items()}
    return out
