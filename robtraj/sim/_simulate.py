"""Scenario → Recording: robot motion, effects, camera visibility and noise."""

from __future__ import annotations

import dataclasses
import datetime
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .._errors import UserError
from ..model import (
    BUILTIN_ROBOTS,
    CameraModel,
    Effects,
    emission_angle,
    flange_poses,
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
from ._scenarios import DEFAULT_DURATION, scenario_moves
from ._unmodelled import describe as describe_unmodelled

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
    ``"unmodelled"``. `commanded` `(P, ·)`: the poses the controller is sent in place of
    the program's targets (e.g. a compensated program, `robtraj compensate`); the
    recording's `/program` keeps the targets (what the robot should reach).
    """
    duration = DEFAULT_DURATION.get(scenario, 30.0) if duration is None else float(duration)
    if not (duration > 0 and np.isfinite(duration)):
        raise UserError(f"duration must be positive, got {duration}")
    if not (0 < rate <= 20000):
        raise UserError(f"rate must be in (0, 20000] Hz, got {rate}")
    if robot not in BUILTIN_ROBOTS:
        raise UserError(f"unknown robot {robot!r} (built in: {', '.join(BUILTIN_ROBOTS)})")
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
    n = int(round(duration * rate))
    t_track = np.arange(n) / rate
    tau = float(effects.time_offset)
    log_time = np.arange(-0.5 + tau, duration + 0.5 + tau, 1.0 / ROBOT_RATE)
    joints, departure, _ = joint_log(model, moves, nominal_fft, Q_SEED, log_time)
    direction = motion_direction(log_time, joints, t_track + tau)
    segment = (np.searchsorted(departure, t_track + tau, side="left") - 1).astype(np.int32)

    temperature = (21.0 + 2.0 * t_track / duration + rng.normal(scale=0.01, size=n)).astype(
        np.float32
    )
    drift = temperature.astype(np.float64) - float(temperature[0])

    tool_wxyz_xyz, leds, theta, inside, sigma = (
        np.asarray(a)
        for a in _observe(
            model,
            effects,
            camera,
            camera_from_base,
            flange_from_tool,
            jnp.asarray(log_time),
            jnp.asarray(joints),
            jnp.asarray(t_track + tau),
            jnp.asarray(direction),
            jnp.asarray(drift),
            jnp.asarray(constellation),
            jnp.asarray(tool.normals),
            jnp.asarray(motion_sign(log_time, joints, t_track + tau)),
        )
    )
    for effect in unmodelled:
        if hasattr(effect, "leds"):
            leds = effect.leds(leds, theta)
    logged = joints
    for effect in unmodelled:
        if hasattr(effect, "log"):
            logged = effect.log(log_time, logged)
    facing = theta < camera.max_emission_angle
    dropped = rng.random(theta.shape) < camera.dropout
    seen = inside & facing & ~dropped
    status = np.where(
        seen, np.where(theta > camera.low_signal_angle, 3, 0), np.where(inside, 1, 2)
    ).astype(np.uint8)
    noisy = leds + sigma[..., None] * rng.normal(size=leds.shape)
    positions = np.where(seen[..., None], noisy, np.nan)

    rec_truth = None
    if truth:
        rec_truth = Truth(
            tool_pose=Pose(np.asarray(tool_wxyz_xyz[:, 4:]), np.asarray(tool_wxyz_xyz[:, :4])),
            camera_from_base=_pose(camera_from_base),
            flange_from_tool=_pose(flange_from_tool),
            constellation=constellation,
            effects={
                **effects.to_dict(),
                **({"unmodelled": describe_unmodelled(unmodelled)} if unmodelled else {}),
            },
        )
    return Recording(
        time=t_track,
        frame_index=np.arange(n, dtype=np.uint64),
        led_ids=tool.led_ids,
        positions=positions,
        status=status,
        temperature=temperature.astype(np.float32),
        robot=RobotLog(time=log_time, joints=logged, model=robot, dh=None),
        program=Program(
            targets=Pose(*targets),
            motion=np.array([m.motion for m in moves]),
            speed=np.array([m.speed for m in moves]),
            segment=segment,
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
