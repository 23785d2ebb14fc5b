"""The optical CMM: measurement volume, LED visibility by emission angle, noise.

Camera frame: origin at the camera's optical centre, z along the optical axis into
the scene. An LED is seen when it lies inside the measurement volume (a cone of
half-angle `fov_half_angle` around z, between `near` and `far`) and the angle between
its emission axis and the line of sight to the camera is below `max_emission_angle`
(LEDs facing away are never seen). Noise is isotropic Gaussian with a standard
deviation that grows toward the edge of visibility and with the distance (the image
spot is smaller and dimmer further away):
``sigma = sigma0 · (1 + edge_gain · (theta / max_emission_angle)^4) ·
(distance / reference_distance)^distance_exponent``.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float


class CameraModel(eqx.Module):
    """Visibility and noise model of a K610-class tracker (SI units)."""

    sigma0: float = 15e-6  # [m] per-axis noise of an LED seen head-on
    edge_gain: float = 4.0  # noise at the visibility edge is (1 + edge_gain)·sigma0
    max_emission_angle: float = float(jnp.deg2rad(65.0))  # [rad]
    low_signal_angle: float = float(jnp.deg2rad(58.0))  # [rad] status 3 beyond this
    fov_half_angle: float = float(jnp.deg2rad(34.0))  # [rad]
    near: float = 1.2  # [m]
    far: float = 6.0  # [m]
    dropout: float = 0.002  # probability that a visible LED is missed in a frame
    reference_distance: float = 2.0  # [m] distance at which the noise is sigma0 head-on
    distance_exponent: float = 2.0  # triangulation: depth noise grows as distance²


def emission_angle(
    leds_camera: Float[Array, "*batch 3"], normals_camera: Float[Array, "*batch 3"]
) -> Float[Array, " *batch"]:
    """Angle [rad] between each LED's emission axis and its line of sight to the camera."""
    to_camera = -leds_camera / jnp.linalg.norm(leds_camera, axis=-1, keepdims=True)
    cos = jnp.sum(to_camera * normals_camera, axis=-1)
    sin = jnp.linalg.norm(jnp.cross(to_camera, normals_camera), axis=-1)
    return jnp.arctan2(sin, cos)


def in_volume(camera: CameraModel, leds_camera: Float[Array, "*batch 3"]) -> Bool[Array, " *batch"]:
    """LED inside the measurement volume (viewing cone between `near` and `far`)."""
    dist = jnp.linalg.norm(leds_camera, axis=-1)
    off_axis = jnp.arccos(jnp.clip(leds_camera[..., 2] / dist, -1.0, 1.0))
    return (dist > camera.near) & (dist < camera.far) & (off_axis < camera.fov_half_angle)


def noise_sigma(
    camera: CameraModel, theta: Float[Array, "*batch"], distance: Float[Array, "*batch"]
) -> Float[Array, "*batch"]:
    """Per-axis noise standard deviation [m] of an LED seen at emission angle `theta`
    [rad] from `distance` [m] (camera frame origin to the LED)."""
    angular = 1.0 + camera.edge_gain * (theta / camera.max_emission_angle) ** 4
    radial = (distance / camera.reference_distance) ** camera.distance_exponent
    return camera.sigma0 * angular * radial
