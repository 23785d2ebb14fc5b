"""The noise of a recording's observations: emission angles from per-frame tool poses,
and the per-observation variance under the noise model estimated from the recording
(`estimate_noise`)."""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Float

from ..recording import Recording, finite_points
from ._chunks import CHUNK, Columns, chunk_length, over_frames
from ._exact_median import ExactMedian
from ._noise import NoiseModel, noise_and_variance, noise_from_triples, pick_triples
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


def _tool_columns(rec: Recording) -> np.ndarray:
    """Recording columns of the tool's LEDs (all without a tool)."""
    ids = np.asarray(rec.led_ids)
    if rec.tool is None:
        return np.arange(ids.size)
    return np.flatnonzero(np.isin(ids, np.asarray(rec.tool.led_ids)))


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
    cols = _tool_columns(rec)
    pos = rec.positions if cols.size == ids.size else rec.positions[:, cols]
    th = angles if cols.size == ids.size else angles[:, cols]
    model, v = noise_and_variance(pos, th, ids[cols])
    var = np.full(angles.shape, np.nan)
    var[:, cols] = v
    return model, np.where(rec.visible, var, np.nan)


@dataclasses.dataclass(frozen=True, eq=False)
class ObservationVariance:
    """The noise model's per-axis variance [m²] of any frames of a recording, from the
    compact state it needs (`observation_noise_source`): the model, its LEDs' recording
    columns `cols`, the per-frame tool poses the emission angles come from (camera←tool,
    `(N, 3)`, `(N, 4)`, `valid` `(N,)`), the constellation and normals of those LEDs
    and the median angle that stands in where a frame has no pose. `at` gives what
    `observation_noise` gives, frame by frame."""

    model: NoiseModel | None
    cols: np.ndarray
    position: np.ndarray | None
    quaternion_wxyz: np.ndarray | None
    valid: np.ndarray | None
    constellation: np.ndarray
    normals: np.ndarray | None
    fill: float

    def angles(self, rows: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Emission angles [rad] `(len(rows), len(cols))` of recording frames `rows`
        whose positions (model columns) are `x`: NaN where unseen or without a pose, as
        `observation_angles`."""
        if self.normals is None:
            return np.full(x.shape[:2], np.nan)
        th = led_emission_angles(
            self.position[rows], self.quaternion_wxyz[rows], self.constellation, self.normals
        )
        return np.where(finite_points(x) & self.valid[rows, None], th, np.nan)

    def at(self, rows: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The variance `(len(rows), M)` [m²] of recording frames `rows` whose positions
        (all the recording's columns) are `x` [m]: NaN where unseen or not on the tool."""
        xc = x[:, self.cols]
        th = self.angles(rows, xc) if self.model.angle_knots.size > 1 else None
        th = np.zeros(xc.shape[:2]) if th is None else np.where(np.isfinite(th), th, self.fill)
        var = np.full(x.shape[:2], np.nan)
        var[:, self.cols] = self.model.observation_variance(xc, th)
        return np.where(finite_points(x), var, np.nan)


def observation_noise_source(
    rec: Recording, chunk: int = CHUNK
) -> tuple[NoiseModel, ObservationVariance]:
    """`observation_noise` of a recording of any length, in passes over its frames
    (`rec` in memory or opened lazily): the same model, and the per-observation variance
    as an `ObservationVariance` that computes it for any frames instead of the
    `(frames, leds)` array. Raises `UserError` as `observation_noise`."""
    ids = np.asarray(rec.led_ids)
    cols = _tool_columns(rec)
    source = Columns(rec.positions, cols)
    n = source.shape[0]
    pose = {"position": None, "quaternion_wxyz": None, "valid": None}
    const = np.zeros((cols.size, 3))
    normals = None
    if rec.tool is not None and rec.tool.normals is not None and rec.tool.constellation is not None:
        est = estimate_poses(rec, weighting="uniform", register=False, leds=rec.led_ids)
        pose = {
            "position": est.position,
            "quaternion_wxyz": est.quaternion_wxyz,
            "valid": est.valid,
        }
        del est
        row = {int(i): k for k, i in enumerate(np.asarray(rec.tool.led_ids))}
        rows = np.array([row[int(i)] for i in ids[cols]])
        const = np.asarray(rec.tool.constellation, np.float64)[rows]
        normals = np.asarray(rec.tool.normals, np.float64)[rows]
    src = ObservationVariance(None, cols, **pose, constellation=const,
                              normals=normals, fill=0.0)  # fmt: skip
    size = chunk_length(n, chunk)
    starts = {True: np.zeros(max(n - 2, 0), bool), False: np.zeros(max(n - 2, 0), bool)}
    median = ExactMedian()

    def seen_by(x, th, with_angle):
        seen = finite_points(x)
        return seen & np.isfinite(th) if with_angle else seen

    def triples(seen):
        return seen[:-2] & seen[1:-1] & seen[2:]  # rows: first frames of the triples

    def first(a, x):
        th = src.angles(np.arange(a, a + x.shape[0]), x)
        median.count(th[:size])
        for with_angle in (True, False):
            trip = triples(seen_by(x, th, with_angle))[:size]
            starts[with_angle][a : a + trip.shape[0]] = trip.sum(1) >= 2

    over_frames(source, first, size, extra=2)
    has_angle = median.n > 0
    cand = pick_triples(starts[has_angle])
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def second(a, x):
        th = src.angles(np.arange(a, a + x.shape[0]), x)
        if has_angle:
            median.keep(th[:size])
        mine = cand[(cand >= a) & (cand < a + size)]
        if mine.size:
            th = th if has_angle else np.zeros(th.shape)
            rows = (mine - a)[:, None] + np.arange(3)
            seen = triples(seen_by(x, th, has_angle))[mine - a]
            parts.append((x[rows], th[rows], seen))

    over_frames(source, second, size, extra=2)
    pos, th, seen = (np.concatenate(p) for p in zip(*parts))
    model = noise_from_triples(pos, th, seen, ids[cols], has_angle=has_angle)
    fill = median.value() if has_angle else 0.0
    return model, dataclasses.replace(src, model=model, fill=fill)
