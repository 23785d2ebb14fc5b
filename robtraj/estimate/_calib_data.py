"""Bundle-calibration input: a `Recording` checked and described by compact per-frame
arrays (which LEDs each frame sees, times, motion signs; its positions stay in the
recording, read by frame ranges), with the weights of its observations.

Everything here is NumPy and runs once per fit, in one pass over the frames. Bad input a user can fix (no robot log,
no tool, no overlap between the robot and tracker clocks, too few LED observations)
raises `UserError` with a one-line message. `observations` is the first step of a fit:
what it takes from the recording, with the recording's noise model estimated on a
background thread meanwhile (`observation_weights` waits for it).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

import numpy as np

from .._errors import UserError
from ..model import (
    MOTION_THRESHOLD,
    RobotModel,
    motion_direction,
    motion_sign,
    robot_from_log,
)
from ..recording import Recording, finite_points
from ._calib_frames import Weights, read_rows
from ._chunks import Columns, over_frames
from ._compile_ahead import in_background
from ._observation_noise import observation_noise_source

#: minimum number of tracker frames inside the robot log's time span
MIN_OVERLAP_FRAMES = 10


@dataclasses.dataclass(frozen=True)
class CalibrationData:
    """A recording prepared for the bundle calibration (NumPy, SI units).

    Frames are the tracker frames inside the robot log's time span that see at least
    one LED of the tool; LEDs are the tool's LEDs that the tracker sees somewhere.

    - `time` `(n,)` tracker clock [s]; `frame` `(n,)` index into the recording's frames.
    - `positions`: the recording's `(N, M, 3)` LED positions in the camera frame [m]
      (NaN where unseen; in memory or read by frame ranges, `robtraj.open_recording`),
      never copied whole: `measured` reads the fit's frames and LEDs.
    - `seen` `(n, m)` bool.
    - `direction` `(n, joints)` int8 sign of each joint's motion (for `backlash`);
      `moving` `(n, joints)` int8 sign of each joint's velocity, 0 slower than
      `motion_threshold` [rad/s] (`motion_sign`).
    - `drift` `(n,)` drift variable of `thermal_drift`: camera temperature change [K]
      since the first frame, or minutes since the first frame without temperatures.
    - `log_time` `(k,)`, `joints` `(k, joints)`: the robot log (robot clock).
    - `led_ids` `(m,)`, `reference` `(m, 3)` the reference constellation the gauge and
      the initial values refer to, `normals` `(m, 3)` (zeros when the tool has none).
    - `unseen_leds`: ids of tool LEDs never seen (kept at the reference, not estimated);
      `led_seen` `(m,)` the complement as a mask.
    - `columns` `(m,)` each LED's column in the recording, which has
      `n_recording_frames` frames and `n_recording_leds` LEDs.
    """

    robot: RobotModel
    time: np.ndarray
    frame: np.ndarray
    positions: Any
    seen: np.ndarray
    direction: np.ndarray
    moving: np.ndarray
    drift: np.ndarray
    log_time: np.ndarray
    joints: np.ndarray
    led_ids: np.ndarray
    reference: np.ndarray
    normals: np.ndarray
    has_normals: bool
    nominal_flange_from_tool: np.ndarray  # (7,) wxyz_xyz
    reference_leds: np.ndarray
    unseen_leds: tuple[int, ...]
    led_seen: np.ndarray
    n_recording_frames: int
    columns: np.ndarray
    n_recording_leds: int
    motion_threshold: float = MOTION_THRESHOLD

    def joints_at(self, idx: np.ndarray, time_offset: float = 0.0) -> np.ndarray:
        """Logged joint angles `(len(idx), joints)` at frames `idx` (robot clock t + τ),
        linearly interpolated (for grouping frames into robot poses)."""
        t = self.time[idx] + time_offset
        return np.stack([np.interp(t, self.log_time, q) for q in self.joints.T], -1)

    def measured(self, idx: np.ndarray) -> np.ndarray:
        """LED positions `(len(idx), m, 3)` [m] at the increasing frames `idx` (into
        `data`), 0 where unseen."""
        x = read_rows(self.positions, self.frame[idx])[:, self.columns]
        return np.where(self.seen[idx][..., None], x, 0.0)

    def measured_sum(self, idx: np.ndarray, block: int = 1 << 16) -> np.ndarray:
        """``measured(idx).sum(0)`` `(m, 3)` [m], read `block` frames at a time and summed
        in the same order (frame after frame)."""
        total = np.zeros((self.n_leds, 3))
        for a in range(0, idx.size, block):
            total = np.concatenate([total[None], self.measured(idx[a : a + block])]).sum(0)
        return total

    @property
    def n_frames(self) -> int:
        return int(self.time.shape[0])

    @property
    def n_leds(self) -> int:
        return int(self.led_ids.shape[0])


@dataclasses.dataclass(frozen=True)
class _Checked:
    """What `check` found usable in a recording (the input of `prepare`)."""

    robot: RobotModel
    log_time: np.ndarray
    joints: np.ndarray
    reference: np.ndarray
    tool_ids: np.ndarray
    cols: np.ndarray  # each tool LED's column in the recording, −1 where absent
    time: np.ndarray
    inside: np.ndarray  # tracker frames inside the robot log's time span


def check(
    rec: Recording, *, time_offset: float = 0.0, constellation: np.ndarray | None = None
) -> _Checked:
    """The checks of `prepare` on `rec`, without its work on the observations: raises
    `UserError` (one line) for what a user can fix."""
    if rec.robot is None:
        raise UserError("the recording has no robot log (/robot): calibration needs joint angles")
    if rec.tool is None:
        raise UserError("the recording has no tool description (/tool): nothing to calibrate")
    if rec.robot.time.shape[0] < 2:
        raise UserError("the robot log has fewer than 2 samples")
    robot = robot_from_log(rec.robot)
    if rec.robot.joints.shape[1] != robot.n_joints:
        raise UserError(
            f"/robot/joints has {rec.robot.joints.shape[1]} joints, the robot model {robot.n_joints}"
        )
    log_time = np.asarray(rec.robot.time, np.float64)
    joints = np.asarray(rec.robot.joints, np.float64)
    bad = ~np.isfinite(log_time) | ~np.all(np.isfinite(joints), axis=1)
    if bad.any():
        raise UserError(
            f"the robot log has {int(bad.sum())} samples with a non-finite time or joint angle "
            f"(first at sample {int(np.argmax(bad))}): calibration needs finite joint angles"
        )
    if not np.all(np.isfinite(np.asarray(rec.time, np.float64))):
        raise UserError("the tracker frames have non-finite time stamps (/tracker/time)")

    tool = rec.tool
    ref = np.asarray(tool.constellation if constellation is None else constellation, np.float64)
    if ref.shape != np.shape(tool.constellation):
        raise UserError(f"constellation has shape {ref.shape}, the tool {tool.constellation.shape}")
    col = {int(i): k for k, i in enumerate(np.asarray(rec.led_ids))}
    tool_ids = np.asarray(tool.led_ids, np.int64)
    cols = np.array([col.get(int(i), -1) for i in tool_ids])
    if not np.any(cols >= 0):
        raise UserError("none of the tool's LEDs appears in /tracker/led_ids")

    t = np.asarray(rec.time, np.float64)
    inside = (t + time_offset >= log_time[0]) & (t + time_offset <= log_time[-1])
    if inside.sum() < MIN_OVERLAP_FRAMES:
        raise UserError(
            f"the robot log ({log_time[0]:.3f} s to {log_time[-1]:.3f} s, robot clock) and the "
            f"tracker frames ({t[0]:.3f} s to {t[-1]:.3f} s) overlap in only {int(inside.sum())} "
            f"frames (need {MIN_OVERLAP_FRAMES}); are both clocks in the same time base?"
        )
    return _Checked(robot, log_time, joints, ref, tool_ids, cols, t, inside)


def prepare(
    rec: Recording,
    *,
    time_offset: float = 0.0,
    constellation: np.ndarray | None = None,
    motion_threshold: float = MOTION_THRESHOLD,
    checked: _Checked | None = None,
) -> CalibrationData:
    """Check `rec` and build the `CalibrationData` (see there).

    `time_offset` [s] is the clock offset used for the backlash motion direction;
    `constellation` `(tool LEDs, 3)` [m] replaces the nominal one as the reference;
    `motion_threshold` [rad/s] the speed below which a joint counts as at rest;
    `checked`: `check`'s result for the same arguments, if the caller has it.
    """
    c = checked or check(rec, time_offset=time_offset, constellation=constellation)
    robot, log_time, joints, ref, tool_ids = c.robot, c.log_time, c.joints, c.reference, c.tool_ids
    cols, t, inside, tool = c.cols, c.time, c.inside, rec.tool
    have = cols >= 0
    led_keep = have  # every tool LED the tracker reports (fixed shapes across recordings)
    seen = _seen(rec.positions, cols[have])
    never = np.zeros(have.size, bool)
    never[have] = ~seen[inside].any(0)
    frame_keep = inside & seen.any(1)
    frames = np.flatnonzero(frame_keep)
    if frames.size < t.shape[0]:
        seen = seen[frames]
    if seen.sum() < 10:
        raise UserError(
            f"only {int(seen.sum())} finite LED observations overlap the robot log (need 10)"
        )

    if rec.temperature is not None and np.all(np.isfinite(rec.temperature)):
        temp = np.asarray(rec.temperature, np.float64)
        drift = temp[frames] - temp[0]
    else:
        drift = (t[frames] - t[0]) / 60.0
    direction = motion_direction(log_time, joints, t[frames] + time_offset)
    normals = tool.normals
    ffs = tool.flange_from_tool
    nominal_fft = (
        np.array([1.0, 0, 0, 0, 0, 0, 0])
        if ffs is None
        else np.concatenate([ffs.quaternion_wxyz, ffs.position]).astype(np.float64)
    )
    return CalibrationData(
        robot=robot,
        time=t[frames],
        frame=frames,
        positions=rec.positions,
        seen=seen,
        direction=_signs(direction),
        moving=_signs(motion_sign(log_time, joints, t[frames] + time_offset, motion_threshold)),
        motion_threshold=float(motion_threshold),
        drift=drift,
        log_time=log_time,
        joints=joints,
        led_ids=tool_ids[led_keep],
        reference=ref[led_keep],
        normals=np.zeros_like(ref[led_keep])
        if normals is None
        else np.asarray(normals, np.float64)[led_keep],
        has_normals=normals is not None,
        nominal_flange_from_tool=nominal_fft,
        reference_leds=np.asarray(
            tool.reference_leds if tool.reference_leds is not None else tool_ids[:3]
        ),
        unseen_leds=tuple(int(i) for i in tool_ids[never]),
        led_seen=seen.any(0) if seen.size else np.zeros(int(have.sum()), bool),
        n_recording_frames=int(t.shape[0]),
        columns=cols[led_keep],
        n_recording_leds=rec.n_leds,
    )


def _seen(positions, cols: np.ndarray) -> np.ndarray:
    """`(N, len(cols))` bool: the LEDs of recording columns `cols` seen per frame, in one
    pass over the frames."""
    source = Columns(positions, cols)
    out = np.empty(source.shape[:2], bool)

    def visit(a, x):
        out[a : a + x.shape[0]] = finite_points(x)

    over_frames(source, visit)
    return out


def _signs(x) -> np.ndarray:
    """Motion signs (−1, 0, 1) as int8: exactly the values, in an eighth of the memory."""
    return np.asarray(x).astype(np.int8)


@dataclasses.dataclass(frozen=True)
class Observations:
    """What a fit takes from a recording: its observations `data`, the constellation the
    fit starts from per LED of `data` (`start`: `init`'s, else the reference), the clock
    offset they were prepared with [s], the recording's `/probe` poses, and what the
    weights will be made of: the user's `weights` (recording-shaped) or, while it is
    estimated on a background thread, the recording's `noise` model."""

    data: CalibrationData
    start: np.ndarray
    time_offset: float
    probe: Any
    weights: np.ndarray | None
    noise: Future | None


def observations(
    rec: Recording,
    init,
    weights: np.ndarray | None,
    motion_threshold: float | None,
    noise: bool,
    say: Callable[[str], None],
) -> Observations:
    """`rec` checked and prepared (`check`, `prepare`) at `init`'s clock offset, gauge
    reference and motion threshold (a `CalibrationResult`, or None for the nominal
    constellation, no offset and `MOTION_THRESHOLD`; `motion_threshold` overrides it);
    with `noise` and no `weights`, the recording's noise model is estimated on a
    background thread from here on (`observation_noise`)."""
    reference = start = None
    if init is not None and rec.tool is not None:
        reference = _per_tool_led(rec, init.led_ids, init.gauge_reference)
        start = _per_tool_led(rec, init.led_ids, init.constellation)
    tau0 = 0.0 if init is None else init.time_offset
    motion = motion_threshold
    if motion is None:
        motion = MOTION_THRESHOLD if init is None else init.motion_threshold
    if not (np.isfinite(motion) and motion > 0):
        raise UserError(f"the motion threshold must be a positive speed [rad/s], not {motion}")
    checked = check(rec, time_offset=tau0, constellation=reference)
    noise_job = None
    if weights is None and noise:
        say("noise model of the recording")
        noise_job = in_background(observation_noise_source, rec)
    data = prepare(
        rec,
        time_offset=tau0,
        constellation=reference,
        motion_threshold=float(motion),
        checked=checked,
    )
    if start is not None:
        col = {int(i): k for k, i in enumerate(rec.tool.led_ids)}
        start = start[[col[int(i)] for i in data.led_ids]]
    else:
        start = data.reference
    return Observations(data, start, tau0, rec.probe, weights, noise_job)


def observation_weights(obs: Observations) -> tuple[Weights, Any, dict[str, Any]]:
    """The weights [1/m²] of `obs.data`'s observations (`Weights`, computed per block of
    frames), the noise model they come from (None for the user's) and its description:
    the user's weights, else the inverse variances of the recording's noise model
    (waited for), uniform where it could not be estimated; zero where unseen. `UserError`
    for weights of the wrong shape or all zero."""
    noise, info = None, {"kind": "user_weights"}
    if obs.noise is not None:
        try:
            noise, var = obs.noise.result()
        except UserError as err:
            info = {"kind": "uniform", "reason": str(err)}
        else:
            return Weights(noise=var), noise, noise.to_dict()
    if obs.weights is None:
        return Weights(), noise, info
    return Weights(user=_checked_weights(obs.data, obs.weights)), noise, info


def recording_weights(data: CalibrationData, w: np.ndarray) -> np.ndarray:
    """The weights `w` of `data`'s observations in the recording's frames and LED
    columns (0 elsewhere): what `observation_weights` takes back as the user's."""
    out = np.zeros((data.n_recording_frames, data.n_recording_leds))
    out[np.ix_(data.frame, data.columns)] = w
    return out


def _checked_weights(data: CalibrationData, weights: np.ndarray) -> np.ndarray:
    """Recording-shaped `weights` (`UserError` for a wrong shape, or none positive at
    `data`'s observations)."""
    w = np.asarray(weights, float)
    shape = (data.n_recording_frames, data.n_recording_leds)
    if w.shape != shape:
        raise UserError(f"weights have shape {w.shape}, expected {shape}")
    at = w[data.frame][:, data.columns]
    if not np.any(data.seen & np.isfinite(at) & (at > 0)):
        raise UserError("all weights are zero")
    return w


def _per_tool_led(rec: Recording, ids, values) -> np.ndarray:
    """`values` (rows per `ids`) as rows per tool LED; the nominal where `ids` lacks one."""
    row = {int(i): k for k, i in enumerate(ids)}
    vals = np.asarray(values, float)
    return np.array(
        [
            vals[row[int(i)]] if int(i) in row else rec.tool.constellation[k]
            for k, i in enumerate(rec.tool.led_ids)
        ]
    )
