"""The noise of a recording's observations: emission angles from per-frame tool poses,
and the per-observation variance under the noise model estimated from the recording
(`estimate_noise`)."""

from __future__ import annotations

import numpy as np
from jaxtyping import Float

from ..recording import Recording
from ._noise import NoiseModel, noise_and_variance
from ._poses import estimate_poses, led_emission_angles


def observation_angles(rec: Recording) -> Float[np.ndarray, "frames leds"]:
    """Emission angle [rad] of every observation `(N, M)` of `rec`, from per-frame tool
    poses (uniform Procrustes on the nominal constellation), independent of any robot
    model or calibration. NaN where the LED is unseen, is not on the tool, or the frame
    has no pose; all NaN when the tool has no LED normals."""
    n, m = rec.positions.shape[:2]
    if rec.tool is None or rec.tool.normals is None or rec.tool.constellation is None:
        return np.full((n, m), np.nan)
    est = estimate_poses(rec, weighting="uniform", register=False, leds=rec.led_ids)
    row = {int(i): k for k, i in enumerate(np.asarray(rec.tool.led_ids))}
    rows = np.array([row.get(int(i), -1) for i in rec.led_ids])
    on_tool = rows >= 0
    const = np.where(on_tool[:, None], np.asarray(rec.tool.constellation)[rows], 0.0)
    normals = np.where(on_tool[:, None], np.asarray(rec.tool.normals)[rows], 0.0)
    ang = led_emission_angles(est.position, est.quaternion_wxyz, const, normals)
    return np.where(rec.visible & est.valid[:, None] & on_tool[None], ang, np.nan)


def observation_noise(
    rec: Recording, angles: Float[np.ndarray, "frames leds"] | None = None
) -> tuple[NoiseModel, Float[np.ndarray, "frames leds"]]:
    """The noise model of `rec`'s tool LEDs (`estimate_noise`) and the per-axis variance
    [m²] `(N, M)` it gives every observation: NaN where unseen or not on the tool; an
    observation without an emission angle (its frame has no pose) gets the variance at
    the median angle. `angles`: `observation_angles(rec)` if already computed.

    Raises `UserError` when the recording holds too few runs of consecutive frames."""
    if angles is None:
        angles = observation_angles(rec)
    ids = np.asarray(rec.led_ids)
    on_tool = (
        np.isin(ids, np.asarray(rec.tool.led_ids))
        if rec.tool is not None
        else np.ones(ids.size, bool)
    )
    cols = np.flatnonzero(on_tool)
    pos = rec.positions if cols.size == ids.size else rec.positions[:, cols]
    th = angles if cols.size == ids.size else angles[:, cols]
    model, v = noise_and_variance(pos, th, ids[cols])
    var = np.full(angles.shape, np.nan)
    var[:, cols] = v
    return model, np.where(rec.visible, var, np.nan)
