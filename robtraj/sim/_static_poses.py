"""Static poses of a nominal UR10 measured by a 6-DOF tracker: a pose series with known
truth (the robot is the nominal one, its controller logs what `hidden` effects make it
log), for the pose-level fit's tests and coverage studies."""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from ..model import Effects, flange_poses, ur10

#: tracker noise of a static pose: position [m] and rotation [rad] per axis
POSE_NOISE = (20e-6, 2e-5)
#: joint ranges [rad] the poses are drawn from (those of the UR10 Series B)
UR10_RANGES = ((-3.1, -0.8), (-2.4, 0.1), (-2.2, 2.2), (-3.5, 0.0), (-2.5, 0.1), (-1.0, 1.0))


def static_pose_series(
    n: int,
    seed: int,
    hidden: Sequence = (),
    noise: tuple[float, float] = POSE_NOISE,
    ranges: Sequence[tuple[float, float]] = UR10_RANGES,
) -> tuple[np.ndarray, np.ndarray]:
    """`n` static poses of a nominal UR10 at joint angles uniform in `ranges` (seeded),
    each measured as tracker←probe with Gaussian `noise` (position [m], rotation [rad]
    per axis, applied in the probe frame). The tracker is at a fixed pose, the probe
    10 mm off and 90 mm out of the flange. Returns the logged joint angles `(n, 6)`
    [rad] (the true ones as the `hidden` effects of `robtraj.sim` make the controller
    log them) and the measured poses `(n, 7)` (wxyz, xyz [m])."""
    rng = np.random.default_rng(seed)
    q = np.stack([rng.uniform(lo, hi, n) for lo, hi in ranges], 1)
    log = q.copy()
    for e in hidden:
        log = e.log(np.arange(n, dtype=float), log)
    fl = jax.jit(flange_poses)(ur10(), Effects.zeros(6), jnp.asarray(q), jnp.zeros((n, 6)))
    cam = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_z_radians(0.6), jnp.array([2.0, -1.0, 0.4])
    )
    probe = jaxlie.SE3.from_translation(jnp.array([0.0, 0.01, 0.09]))
    pose = jax.vmap(lambda f: cam @ jaxlie.SE3(f) @ probe)(fl.wxyz_xyz)
    tangent = np.concatenate([rng.normal(0, noise[0], (n, 3)), rng.normal(0, noise[1], (n, 3))], 1)
    noisy = jax.vmap(lambda p, d: jaxlie.SE3(p) @ jaxlie.SE3.exp(d))(
        pose.wxyz_xyz, jnp.asarray(tangent)
    )
    return log, np.asarray(noisy.wxyz_xyz)
