"""Scenario → Recording: `simulate` in memory, `simulate_to` straight to a file.

Both take the frames a chunk at a time from one generator (`._generate`), so that
`simulate_to` writes a recording of any length in bounded memory.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .._errors import UserError
from .._progress import progress_bar, progress_status
from .._recording_writer import RecordingWriter, frame_arrays, with_frame_arrays
from ..model import BUILTIN_ROBOTS, CameraModel, Effects, flange_poses, hemispherical_tool
from ..recording import Pose, Recording
from ._generate import (
    Q_SEED as Q_SEED,  # the robot's start configuration (for tests)
    frame_chunks,
    simulation_plan,
)
from ._motion import Move


@dataclasses.dataclass(frozen=True)
class SimulatedFile:
    """What `simulate_to` wrote: the recording at `path`, `n_frames` frames of `n_leds`
    LEDs over `time_span` [s] (first to last frame), with on average `seen_mean` and at
    least `seen_min` LEDs seen per frame."""

    path: Path
    n_frames: int
    n_leds: int
    time_span: float
    seen_mean: float
    seen_min: int


def simulate(
    scenario: str = "paper",
    *,
    seed: int = 0,
    duration: float | None = None,
    rate: float = 1000.0,
    effects: Effects | dict | None = None,
    camera: CameraModel | None = None,
    robot: str = "abb_irb2400_16",
    truth: bool = True,
    moves: Sequence[Move] | None = None,
    unmodelled: Sequence = (),
    commanded: Pose | None = None,
    controller_errors: bool = True,
) -> Recording:
    """Simulate a tracker recording of `scenario` (seeded, reproducible).

    Tracker at `rate` Hz on its own clock (t = 0 at the first frame), the robot's joint
    log at 250 Hz on the robot clock (robot time = tracker time + `time_offset`). The
    true camera placement, flange←tool and constellation differ from nominal by a
    seeded perturbation (a few cm / degrees for the camera, ~0.5 mm / 0.3° for the tool
    mount, ~50 µm per LED); the recording carries the nominal tool and, unless
    `truth=False`, the truth in `/truth`. `moves`: a program of the caller's (e.g. from
    `joint_dwells`) instead of the scenario's; the truth is that of the same `seed`.
    `unmodelled`: physics outside robtraj's model (`robtraj.sim.PeriodicJointError`,
    `VelocityDeadbandError`, `SightLineBias`), described in the truth's effects under
    ``"unmodelled"``; an effect's ``leds(leds, theta)`` must act frame by frame (the
    frames are generated in chunks). `commanded` `(P, ·)`: the poses the controller is
    sent in place of the program's targets (e.g. a compensated program, `robtraj
    compensate`); the recording's `/program` keeps the targets (what the robot should
    reach). `controller_errors=False`: the controller attains what it is sent exactly
    (the program's injected approach, drift and ringing errors, e.g. `iso_cube`'s ISO 9283
    truths, left out).

    The whole recording is returned in memory; `simulate_to` writes the same recording
    to a file as it is generated, in memory independent of its length.
    """
    plan = simulation_plan(
        scenario,
        seed=seed,
        duration=duration,
        rate=rate,
        effects=effects,
        camera=camera,
        robot=robot,
        truth=truth,
        moves=moves,
        unmodelled=unmodelled,
        commanded=commanded,
        controller_errors=controller_errors,
    )
    n = plan.n_frames
    arrays = {k: np.empty((n, *a.shape[1:]), a.dtype) for k, a in frame_arrays(plan.header).items()}
    start = 0
    for chunk in frame_chunks(plan):
        for k, a in frame_arrays(chunk).items():
            arrays[k][start : start + a.shape[0]] = a
        start += chunk.n_frames
    return with_frame_arrays(plan.header, arrays)


def simulate_to(
    path: str | os.PathLike,
    scenario: str = "paper",
    *,
    overwrite: bool = False,
    progress: bool | None = None,
    **options: Any,
) -> SimulatedFile:
    """Simulate a recording of `scenario` and write it to `path` as it is generated.

    The file holds what ``write_recording(simulate(scenario, **options), path)`` writes
    (`options`: `simulate`'s keyword arguments), but only a chunk of tracker frames
    (`CHUNK_FRAMES`) is in memory at a time, beside the program and the robot's 250 Hz
    joint log, which grow with the duration (computing the log of an hour takes about
    0.4 GB).
    The file appears under `path` only when complete (a failure or an interrupt leaves
    none); an existing `path` is refused (`UserError`) unless `overwrite`. `progress`: on
    stderr (None: when stderr is a terminal).
    """
    if Path(path).exists() and not overwrite:  # before any work
        raise UserError(f"{path} exists; refusing to overwrite it (use --force or another name)")
    with progress_status("simulate: the robot's motion", progress):
        plan = simulation_plan(scenario, **options)
    n, seen_sum, seen_min = plan.n_frames, 0, plan.header.n_leds
    with (
        RecordingWriter(path, plan.header, n, overwrite=overwrite) as out,
        progress_bar("simulate", n, progress) as advance,
    ):
        for chunk in frame_chunks(plan):
            out.append(chunk)
            seen = chunk.visible.sum(1)
            seen_sum += int(seen.sum())
            seen_min = min(seen_min, int(seen.min()))
            advance(chunk.n_frames)
    return SimulatedFile(
        path=Path(path),
        n_frames=n,
        n_leds=plan.header.n_leds,
        time_span=(n - 1) / plan.rate,
        seen_mean=seen_sum / n,
        seen_min=seen_min,
    )


def joint_dwells(
    joints: np.ndarray, *, dwell: float = 1.0, robot: str = "abb_irb2400_16"
) -> list[Move]:
    """Joint moves to the configurations `joints` `(n, joints)` [rad], each followed by a
    `dwell` [s]: the TCP poses (nominal kinematics and tool mount) the simulator's
    program takes (e.g. the poses `robtraj calibrate` suggests measuring next)."""
    model = BUILTIN_ROBOTS[robot]()
    fft = hemispherical_tool().flange_from_tool
    tcp = jaxlie.SE3(jnp.concatenate([jnp.asarray(fft.quaternion_wxyz), jnp.asarray(fft.position)]))
    q = jnp.asarray(np.atleast_2d(joints), jnp.float64)
    fl = flange_poses(model, Effects.zeros(model.n_joints), q, jnp.zeros_like(q))
    pose = jax.vmap(lambda f: (jaxlie.SE3(f) @ tcp).wxyz_xyz)(fl.wxyz_xyz)
    pose = np.asarray(pose)
    return [Move(p[4:], p[:4], "joint", 0.0, float(dwell)) for p in pose]


#: [rad] the scale of the joint angle error of `calibration_twin`
TWIN_AMPLITUDE = 1e-4


def calibration_twin(seed: int, duration: float, amplitude: float = TWIN_AMPLITUDE):
    """A ``calibration`` run at 25 Hz of a robot whose joint angles are off by a smooth
    error the calibration model does not contain (`joint_harmonics` of seed
    ``1000 + seed``, scale `amplitude` [rad]): the twin the LED σ coverage is judged on."""
    from ._unmodelled import joint_harmonics

    unmodelled = joint_harmonics(1000 + seed, amplitude)
    return simulate("calibration", seed=seed, duration=duration, rate=25.0, unmodelled=unmodelled)
