"""A simulation's recording, generated chunk by chunk (`simulation_plan`, `frame_chunks`).

`simulation_plan` draws and computes what the whole recording shares: the true camera placement,
tool mount and constellation, the program and the robot's joint log, the recording
without its frames. `frame_chunks` then generates the tracker frames `CHUNK_FRAMES` at a time:
robot motion, effects, camera visibility and noise. The chunk size changes nothing in
the recording (the random numbers are one stream, whatever the chunks).
"""

from __future__ import annotations

import dataclasses
import datetime
from collections.abc import Iterator, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .._errors import UserError
from .._recording_writer import with_frame_arrays
from ..model import (
    BUILTIN_ROBOTS,
    CameraModel,
    Effects,
    emission_angle,
    hemispherical_tool,
    in_volume,
    interpolate_joints,
    led_positions,
    motion_direction,
    motion_sign,
    noise_sigma,
    predict_tool_poses,
)
from ..recording import Pose, Program, Recording, RobotLog, Truth
from ._motion import Move, joint_log
from ._scenarios import DEFAULT_DURATION, ideal_controller, scenario_moves
from ._unmodelled import describe as describe_unmodelled

#: tracker frames generated at a time: bounds the memory a simulation takes
CHUNK_FRAMES = 2**15
ROBOT_RATE = 250.0  # [Hz] joint log rate of the controller
#: nominal camera placement: at (3.2, 0, 1.0) m in the base frame, optical axis along −x
NOMINAL_BASE_FROM_CAMERA = jaxlie.SE3.from_rotation_and_translation(
    jaxlie.SO3.from_matrix(jnp.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])),
    jnp.array([3.2, 0.0, 1.0]),
)
Q_SEED = np.array([0.0, 0.3, 0.2, 0.0, -0.5, 0.0])


def _random_se3(rng: np.random.Generator, angle: float, shift: float) -> jaxlie.SE3:
    rotvec = rng.normal(size=3)
    rotvec *= angle / np.linalg.norm(rotvec)
    return jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.exp(jnp.asarray(rotvec)), jnp.asarray(rng.normal(scale=shift, size=3))
    )


def _pose(t: jaxlie.SE3) -> Pose:
    return Pose(np.asarray(t.translation()), np.asarray(t.rotation().wxyz))


@jax.jit
def _observe(
    robot,
    effects,
    camera,
    camera_from_base,
    flange_from_tool,
    log_time,
    joints,
    t,
    direction,
    drift,
    p,
    n,
    moving,
):
    q = interpolate_joints(log_time, joints, t)
    tool = predict_tool_poses(
        robot, effects, camera_from_base, flange_from_tool, q, direction, drift, moving
    )
    leds = led_positions(tool, effects, p, n)
    normals = jax.vmap(lambda T: jax.vmap(T.rotation().apply)(n))(tool)
    theta = emission_angle(leds, normals)
    return (
        tool.wxyz_xyz,
        leds,
        theta,
        in_volume(camera, leds),
        noise_sigma(camera, theta, jnp.linalg.norm(leds, axis=-1)),
    )


@dataclasses.dataclass(frozen=True, eq=False)
class Plan:
    """Everything a simulation draws or computes once: the recording without its frames
    (`header`), and what generating its `n_frames` tracker frames needs."""

    header: Recording
    n_frames: int
    rate: float
    duration: float
    model: Any
    effects: Effects
    camera: CameraModel
    camera_from_base: jaxlie.SE3
    flange_from_tool: jaxlie.SE3
    constellation: jax.Array
    normals: jax.Array
    #: the true joint log on the robot clock `(K,)`, `(K, J)` (before unmodelled effects)
    log_time: np.ndarray
    joints: np.ndarray
    #: per log sample: `motion_direction` and `motion_sign` of the joints `(K, J)`
    direction: np.ndarray
    moving: np.ndarray
    #: robot time at which the move to each target starts `(P,)`
    departure: np.ndarray
    unmodelled: tuple
    #: the random stream, where the per-frame draws start (never advanced: forked)
    rng: np.random.Generator


def simulation_plan(
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
) -> Plan:
    """The plan of ``simulate(scenario, ...)`` (the same arguments, checked here:
    `UserError`), with every random number drawn but the per-frame ones."""
    duration = DEFAULT_DURATION.get(scenario, 30.0) if duration is None else float(duration)
    if not (duration > 0 and np.isfinite(duration)):
        raise UserError(f"duration must be positive, got {duration}")
    if not (0 < rate <= 20000):
        raise UserError(f"rate must be in (0, 20000] Hz, got {rate}")
    if robot not in BUILTIN_ROBOTS:
        raise UserError(f"unknown robot {robot!r} (built in: {', '.join(BUILTIN_ROBOTS)})")
    n = int(round(duration * rate))
    if n < 1:
        raise UserError(f"{duration:g} s at {rate:g} Hz is not a single tracker frame")
    rng = np.random.default_rng(seed)
    model = BUILTIN_ROBOTS[robot]()
    camera = CameraModel() if camera is None else camera
    if effects is None:
        effects = Effects.zeros(model.n_joints)
    elif isinstance(effects, dict):
        effects = Effects.from_dict(effects, model.n_joints)
    tool = hemispherical_tool()

    # truth: perturbed camera placement, tool mount and constellation
    camera_from_base = (
        NOMINAL_BASE_FROM_CAMERA @ _random_se3(rng, np.deg2rad(2.0), 0.03)
    ).inverse()
    nominal_fft = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3(jnp.asarray(tool.flange_from_tool.quaternion_wxyz)),
        jnp.asarray(tool.flange_from_tool.position),
    )
    flange_from_tool = nominal_fft @ _random_se3(rng, np.deg2rad(0.3), 0.5e-3)
    constellation = tool.constellation + rng.normal(scale=50e-6, size=tool.constellation.shape)

    # robot: program → joint log on the robot clock
    moves = scenario_moves(scenario, duration, rng) if moves is None else list(moves)
    if not controller_errors:
        moves = ideal_controller(moves)
    targets = np.stack([m.position for m in moves]), np.stack([m.quaternion_wxyz for m in moves])
    if commanded is not None:
        if np.shape(commanded.position) != targets[0].shape:
            raise UserError(
                f"{np.shape(commanded.position)[0]} commanded poses for {len(moves)} targets"
            )
        moves = [
            dataclasses.replace(m, position=np.asarray(p), quaternion_wxyz=np.asarray(q))
            for m, p, q in zip(moves, commanded.position, commanded.quaternion_wxyz, strict=True)
        ]
    tau = float(effects.time_offset)
    log_time = np.arange(-0.5 + tau, duration + 0.5 + tau, 1.0 / ROBOT_RATE)
    joints, departure, _ = joint_log(model, moves, nominal_fft, Q_SEED, log_time)
    logged = joints
    for effect in unmodelled:
        if hasattr(effect, "log"):
            logged = effect.log(log_time, logged)

    m = tool.led_ids.shape[0]
    rec_truth = None
    if truth:
        rec_truth = Truth(
            tool_pose=Pose(np.zeros((0, 3)), np.zeros((0, 4))),
            camera_from_base=_pose(camera_from_base),
            flange_from_tool=_pose(flange_from_tool),
            constellation=constellation,
            effects={
                **effects.to_dict(),
                **({"unmodelled": describe_unmodelled(unmodelled)} if unmodelled else {}),
            },
        )
    header = Recording(
        time=np.zeros(0),
        frame_index=np.zeros(0, np.uint64),
        led_ids=tool.led_ids,
        positions=np.zeros((0, m, 3)),
        status=np.zeros((0, m), np.uint8),
        temperature=np.zeros(0, np.float32),
        robot=RobotLog(time=log_time, joints=logged, model=robot, dh=None),
        program=Program(
            targets=Pose(*targets),
            motion=np.array([m.motion for m in moves]),
            speed=np.array([m.speed for m in moves]),
            segment=np.zeros(0, np.int32),
        ),
        tool=tool,
        probe=None,
        truth=rec_truth,
        attrs={
            "source": "simulation",
            "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "scenario": scenario,
            "seed": int(seed),
            "rate_hz": float(rate),
        },
    )
    return Plan(
        header=header,
        n_frames=n,
        rate=float(rate),
        duration=duration,
        model=model,
        effects=effects,
        camera=camera,
        camera_from_base=camera_from_base,
        flange_from_tool=flange_from_tool,
        constellation=jnp.asarray(constellation),
        normals=jnp.asarray(tool.normals),
        log_time=log_time,
        joints=joints,
        # at the log's own times: `motion_direction(log_time, joints, t)` is this at the
        # last log sample at or before t (see `_at_log_sample`)
        direction=motion_direction(log_time, joints, log_time),
        moving=motion_sign(log_time, joints, log_time),
        departure=departure,
        unmodelled=tuple(unmodelled),
        rng=rng,
    )


def _fork(rng: np.random.Generator, skip: int = 0) -> np.random.Generator:
    """A copy of `rng` at its state, advanced by `skip` 64-bit draws."""
    bits = type(rng.bit_generator)()
    bits.state = rng.bit_generator.state
    if skip:
        bits.advance(skip)
    return np.random.Generator(bits)


class _Draws:
    """The per-frame random numbers of `n` frames of `m` LEDs as one stream, in this
    order: every frame's temperature noise, then every frame's drop-out draw per LED,
    then every frame's LED noise; handed out chunk by chunk (`take`), each part from a
    fork of the stream at its start. A uniform double takes exactly one 64-bit draw, so
    the LED noise starts `n·m` draws after the drop-outs; the normal draws take a varying
    number, so the temperature noise is drawn twice (once here, only to pass it). The
    numbers do not depend on the chunks they are taken in. `rng`: PCG64 (`advance`), as
    `np.random.default_rng` makes it."""

    def __init__(self, rng: np.random.Generator, n: int, m: int, chunk: int) -> None:
        rng = _fork(rng)
        self._temperature = _fork(rng)
        for start in range(0, n, chunk):
            rng.standard_normal(min(chunk, n - start))
        self._dropout = _fork(rng)
        self._noise = _fork(rng, skip=n * m)
        self._m = m

    def take(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Temperature noise `(k,)` [°C], drop-out draws in [0, 1) `(k, m)`, standard
        normal LED noise `(k, m, 3)` of the next `k` frames."""
        return (
            self._temperature.normal(scale=0.01, size=k),
            self._dropout.random((k, self._m)),
            self._noise.normal(size=(k, self._m, 3)),
        )


def _at_log_sample(log_time: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """`values` of the last log sample at or before each time `t` (the first before the
    log), as `motion_direction` and `motion_sign` look them up."""
    k = np.clip(np.searchsorted(log_time, t, side="right") - 1, 0, len(log_time) - 1)
    return values[k]


def _pad(a: np.ndarray, size: int) -> jax.Array:
    """`a` grown along its first axis to `size` by repeating its last row (every chunk
    then has the shape `_observe` was compiled for)."""
    pad = [(0, size - a.shape[0])] + [(0, 0)] * (a.ndim - 1)
    return jnp.asarray(np.pad(a, pad, mode="edge"))


def frame_chunks(plan: Plan) -> Iterator[Recording]:
    """The frames of the recording `plan` describes, `CHUNK_FRAMES` at a time, each
    chunk a recording like `plan.header` with its frames. The random numbers are the same
    for any chunk size (`_Draws`), and so is the rest up to XLA's rounding (which may
    differ between compiled shapes: on CPU it does not for chunks of 256 frames or more).
    The last chunk is padded to the others' shape for `_observe`: one compilation."""
    n, rate, camera, header = plan.n_frames, plan.rate, plan.camera, plan.header
    size = min(CHUNK_FRAMES, n)
    draws = _Draws(plan.rng, n, header.n_leds, size)
    tau = float(plan.effects.time_offset)
    log_time, joints = jnp.asarray(plan.log_time), jnp.asarray(plan.joints)
    temperature0 = None
    for start in range(0, n, size):
        stop = min(start + size, n)
        k = stop - start
        t = np.arange(start, stop) / rate
        t_robot = t + tau
        temperature_noise, dropout_draw, noise = draws.take(k)
        temperature = (21.0 + 2.0 * t / plan.duration + temperature_noise).astype(np.float32)
        if temperature0 is None:
            temperature0 = float(temperature[0])
        drift = temperature.astype(np.float64) - temperature0

        tool_wxyz_xyz, leds, theta, inside, sigma = (
            np.asarray(a)[:k]
            for a in _observe(
                plan.model,
                plan.effects,
                camera,
                plan.camera_from_base,
                plan.flange_from_tool,
                log_time,
                joints,
                _pad(t_robot, size),
                _pad(_at_log_sample(plan.log_time, plan.direction, t_robot), size),
                _pad(drift, size),
                plan.constellation,
                plan.normals,
                _pad(_at_log_sample(plan.log_time, plan.moving, t_robot), size),
            )
        )
        for effect in plan.unmodelled:
            if hasattr(effect, "leds"):
                leds = effect.leds(leds, theta)
        facing = theta < camera.max_emission_angle
        seen = inside & facing & ~(dropout_draw < camera.dropout)
        status = np.where(
            seen, np.where(theta > camera.low_signal_angle, 3, 0), np.where(inside, 1, 2)
        ).astype(np.uint8)
        positions = np.where(seen[..., None], leds + sigma[..., None] * noise, np.nan)
        segment = np.searchsorted(plan.departure, t_robot, side="left") - 1
        arrays = {
            "tracker/time": t,
            "tracker/frame_index": np.arange(start, stop, dtype=np.uint64),
            "tracker/positions": positions,
            "tracker/status": status,
            "tracker/temperature": temperature,
            "program/segment": segment.astype(np.int32),
        }
        if header.truth is not None:
            arrays["truth/tool_pose/position"] = tool_wxyz_xyz[:, 4:]
            arrays["truth/tool_pose/quaternion_wxyz"] = tool_wxyz_xyz[:, :4]
        yield with_frame_arrays(header, arrays)
