"""Laser-tracker pose series (the ``ipa-robot-accuracy`` data set): static UR10 poses,
their joint angles and temperature, and the measured probe pose (tracker frame, m)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .._errors import UserError
from ..estimate.calibration import robot_world_hand_eye
from ..model import Effects, flange_poses, robot_from_log, ur10

SERIES_FILES = {
    "A": "Series_A/measurements_grid.csv",
    "B": "Series_B/measurements_joint_configurations.csv",
}


def closed_form_start(series: PoseSeries) -> tuple[np.ndarray, np.ndarray]:
    """camera←base and flange←probe (``wxyz_xyz``): Shah's robot-world/hand-eye solution
    on (at most 200) poses, nominal kinematics."""
    robot = ur10()
    sel = np.linspace(0, series.n - 1, min(series.n, 200)).astype(int)
    q = jnp.asarray(series.joints[sel])
    flange = jax.jit(flange_poses)(robot, Effects.zeros(6), q, jnp.zeros_like(q)).wxyz_xyz
    z, x = robot_world_hand_eye(series.measured[sel], np.asarray(flange))
    return np.asarray(z, float), np.asarray(x, float)


# ----------------------------------------------------------------------------- data


@dataclasses.dataclass(frozen=True)
class PoseSeries:
    """Static poses of one measurement series (SI units).

    `measured`: camera←probe `(N, 7)` jaxlie ``wxyz_xyz``; `joints` `(N, 6)` [rad];
    `temperature` `(N,)` [°C] or None; `std` `(N, 6)` tracker standard deviations
    (x, y, z [m], rx, ry, rz [rad]) or None.
    """

    name: str
    joints: np.ndarray
    measured: np.ndarray
    temperature: np.ndarray | None = None
    std: np.ndarray | None = None

    @property
    def start(self) -> tuple[np.ndarray, np.ndarray]:
        """Closed-form camera←base and flange←probe (computed once)."""
        if "_start" not in self.__dict__:
            object.__setattr__(self, "_start", closed_form_start(self))
        return self.__dict__["_start"]

    @property
    def n(self) -> int:
        return int(self.joints.shape[0])

    def subset(self, idx) -> PoseSeries:
        def take(a):
            return None if a is None else np.asarray(a)[idx]

        return PoseSeries(
            self.name,
            self.joints[idx],
            self.measured[idx],
            take(self.temperature),
            take(self.std),
        )

    def every(self, k: int) -> PoseSeries:
        return self.subset(np.arange(0, self.n, int(k)))

    def evenly(self, n: int) -> PoseSeries:
        """`n` poses evenly spaced over the series (all of them if it has fewer). Series
        thinned to the same `n` share every compiled kernel (one compilation, not one
        per series length)."""
        if n >= self.n:
            return self
        return self.subset(np.linspace(0, self.n - 1, int(n)).round().astype(int))

    @property
    def drift_variable(self) -> np.ndarray:
        """Temperature change [K] about the series mean (zeros without temperature)."""
        if self.temperature is None:
            return np.zeros(self.n)
        t = np.asarray(self.temperature, float)
        return t - t.mean()


def _wxyz_xyz_from_matrices(m: np.ndarray) -> np.ndarray:
    return np.asarray(jax.vmap(lambda a: jaxlie.SE3.from_matrix(a).wxyz_xyz)(jnp.asarray(m)))


def load_series(name: str, root: str | Path) -> PoseSeries:
    """Series ``"A"`` (grid) or ``"B"`` (joint configurations) of the data set in `root`
    (the ``ipa-robot-accuracy`` folder) through the pose-CSV importer."""
    from ..importers import load_pose_series

    if name not in SERIES_FILES:
        raise UserError(f"unknown series {name!r} (known: {', '.join(SERIES_FILES)})")
    path = Path(root) / SERIES_FILES[name]
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    joints, measured, _commanded, temperature, std = load_pose_series(path, preset="ipa-ur10")
    if joints is None:
        raise UserError(f"{path}: no joint angles")
    return PoseSeries(
        name,
        np.asarray(joints, float),
        _wxyz_xyz_from_matrices(np.asarray(measured, float)),
        None if temperature is None else np.asarray(temperature, float),
        None if std is None else np.asarray(std, float),
    )


def is_ur10(rec) -> bool:
    """Whether `rec` logs the UR10 the pose fit models (DH table, flange, link masses
    and payload of the built-in ``ur10``)."""
    if rec.robot is None:
        return False
    ours, theirs = ur10(), robot_from_log(rec.robot)
    return ours.dh.shape == theirs.dh.shape and all(
        np.allclose(np.asarray(getattr(ours, f)), np.asarray(getattr(theirs, f)), atol=1e-9)
        for f in ("dh", "last_from_flange", "link_mass", "payload_mass")
    )


def series_from_recording(rec, name: str = "recording") -> PoseSeries:
    """The adapter from an imported `Recording` (``robtraj import --preset ipa-ur10``):
    measured poses from `/probe/tool_pose`, joints from `/robot/joints`, temperature and
    the tracker's `/tracker/pose_std` extra."""
    if rec.probe is None or rec.robot is None:
        raise UserError("the recording has no /probe poses or no /robot joint log")
    if not is_ur10(rec):
        raise UserError(
            f"the pose fit models the UR10 (robot {rec.robot.model!r} logged): 6-DOF pose "
            "series of other robots are not supported yet"
        )
    p = rec.probe.tool_pose
    measured = np.concatenate([p.quaternion_wxyz, p.position], -1)
    std = rec.extras.get("tracker/pose_std") if rec.extras else None
    temp = None if rec.temperature is None else np.asarray(rec.temperature, float)
    return PoseSeries(name, np.asarray(rec.robot.joints, float), measured, temp, std)
