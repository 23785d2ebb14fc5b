"""Static pose accuracy in a recording's report: for an imported 6-DOF pose series, the
measured flange pose of each static pose against the robot model."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._figures import static_pose_figure
from ._html import Figure, Section, Table
from ._report_part import ReportPart


def static_pose_errors(rec, calibration, base_poses) -> tuple[np.ndarray, np.ndarray] | None:
    """Position error [m] and single rotation angle [rad] per frame of a static pose
    series (one robot log sample per tracker frame at the same time, no linear move, no
    segment map: an imported 6-DOF pose series): the measured flange, base←tool ·
    (flange←tool)⁻¹ through the calibration, against the flange pose the robot model
    (with the calibration's effects) gives for the logged joints. None for any other
    recording."""
    import jax.numpy as jnp
    from scipy.spatial.transform import Rotation

    from ..analysis import absolute_pose_error
    from ..model import flange_poses, robot_from_log

    prog, log = rec.program, rec.robot
    if (
        calibration is None
        or base_poses is None
        or log is None
        or (prog is not None and prog.segment is not None)
        or (prog is not None and np.any(np.asarray(prog.motion).astype(str) == "linear"))
        or np.shape(log.joints)[0] != rec.n_frames
        or not np.allclose(log.time, rec.time)
    ):
        return None
    q = jnp.asarray(log.joints, jnp.float64)
    cmd = flange_poses(
        robot_from_log(log),
        calibration.effects_module(q.shape[1]),
        q,
        jnp.zeros_like(q),
    ).wxyz_xyz
    cmd = np.asarray(cmd)
    ft = calibration.flange_from_tool
    r_ft = Rotation.from_quat(ft.quaternion_wxyz, scalar_first=True)
    ok = base_poses.valid
    r_bt = Rotation.from_quat(np.where(ok[:, None], base_poses.quaternion_wxyz, [1, 0, 0, 0]),
                              scalar_first=True)  # fmt: skip
    p_bf = base_poses.position - r_bt.apply(r_ft.inv().apply(ft.position))
    q_bf = (r_bt * r_ft.inv()).as_quat(scalar_first=True)
    p_bf[~ok], q_bf[~ok] = np.nan, np.nan
    return absolute_pose_error(p_bf, q_bf, cmd[:, 4:], cmd[:, :4])


def static_pose_part(out: Path, rec, calibration, base_poses) -> ReportPart:
    """The section of `static_pose_errors` (figure `out/static_poses.png` and a table) and
    its summary line; nothing for a recording that is not a static pose series."""
    static = static_pose_errors(rec, calibration, base_poses)
    if static is None:
        return ReportPart()
    e, a = static
    ok = np.isfinite(e)
    e, a = e[ok], a[ok]
    rms = lambda x: float(np.sqrt(np.mean(x**2)))  # noqa: E731
    fact = (
        "static pose error",
        f"position RMS {rms(e) * 1e3:.3f} mm, max {e.max() * 1e3:.3f} mm; orientation "
        f"RMS {np.degrees(rms(a)):.4f}° over {e.size} poses",
    )
    rows = [
        ["poses", e.size, "–"],
        ["position error, mean", e.mean() * 1e3, "mm"],
        ["position error, RMS", rms(e) * 1e3, "mm"],
        ["position error, max", e.max() * 1e3, "mm"],
        ["orientation error, mean", np.degrees(a.mean()), "°"],
        ["orientation error, RMS", np.degrees(rms(a)), "°"],
        ["orientation error, max", np.degrees(a.max()), "°"],
    ]
    section = Section(
        "Static pose accuracy",
        "Measured flange pose (the measured tool pose through the calibration's "
        "camera←base and flange←tool) against the flange pose of the robot model "
        "for the logged joint angles (nominal kinematics plus the calibrated "
        "effects), pose by pose. The calibration fits the rigid transforms to these "
        "same poses, so this is what the model leaves unexplained; ISO 9283 AP/RP "
        "need repeated cycles.",
        figures=[
            Figure(
                static_pose_figure(out / "static_poses.png", *static),
                "Position and orientation error of each static pose against the "
                "robot model, and their distribution.",
            )
        ],
        tables=[
            Table(
                "Static pose errors",
                ["quantity", "value", "unit"],
                rows,
                "Over the poses where the tool was seen.",
            )
        ],
    )
    return ReportPart(section, (fact,))
