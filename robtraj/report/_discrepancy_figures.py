"""Figures of the discrepancy workflow: the gap step by step, residual structure, the
noise model."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._figures import _save, plt


def gap_figure(
    path, labels: list[str], gaps: list[float], noise: float, floor: float | None = None
) -> Path:
    """Gap [m → µm] after each step, with the per-axis noise level for scale and the
    gap a complete model leaves by chance (`floor`)."""
    fig, ax = plt.subplots(figsize=(7, 3.8), constrained_layout=True)
    x = np.arange(len(gaps))
    ax.bar(x, np.asarray(gaps) * 1e6, color="C0")
    ax.axhline(noise * 1e6, color="C3", ls="--", label=f"noise σ per axis ({noise * 1e6:.1f} µm)")
    if floor is not None:
        ax.axhline(
            floor * 1e6,
            color="C2",
            ls=":",
            label=f"floor of a complete model ({floor * 1e6:.1f} µm)",
        )
    ax.set_xticks(x, ["nominal"] + [f"+ {n}" for n in labels[1:]], rotation=20)
    ax.set_ylabel("gap (systematic RMS) [µm]")
    ax.set_title("Model–measurement gap, step by step")
    ax.legend()
    return _save(fig, path)


def structure_figure(path, before: dict, after: dict) -> Path:
    """Residual RMS [µm] against time, joint 2 and emission angle, before and after."""
    names = list(before)
    fig, axes = plt.subplots(
        1, len(names), figsize=(4 * len(names), 3.6), constrained_layout=True, squeeze=False
    )
    units = {
        "time": ("time [s]", 1.0),
        "joint 2": ("joint 2 [°]", np.degrees(1.0)),
        "emission angle": ("emission angle [°]", np.degrees(1.0)),
    }
    for ax, name in zip(axes[0], names):
        label, scale = units.get(name, (name, 1.0))
        for data, lab in [(before[name], "nominal model"), (after[name], "with named effects")]:
            ax.plot(data[0] * scale, data[1] * 1e6, "o-", ms=3, label=lab)
        ax.set_xlabel(label)
        ax.set_ylabel("residual RMS [µm]")
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend()
    fig.suptitle("Where the model and the measurement disagree")
    return _save(fig, path)


def noise_figure(path, noise) -> Path:
    """The recording's noise model: per-axis σ [µm] against emission angle at the
    distance knots, and against distance at three angles; each LED's level beside."""
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), constrained_layout=True)
    ka, kb = noise.angle_knots, noise.distance_knots
    th = np.linspace(ka[0], ka[-1], 100)
    for r in kb:
        axes[0].plot(
            np.degrees(th), noise.sigma_at(th, np.full_like(th, r)) * 1e6, label=f"{r:.2f} m"
        )
    axes[0].set_xlabel("emission angle [°]")
    axes[0].set_title("σ against emission angle")
    dist = np.linspace(kb[0] - 0.05, kb[-1] + 0.05, 50)
    for a in np.unique(ka[[0, ka.size // 2, -1]]):
        axes[1].plot(
            dist, noise.sigma_at(np.full_like(dist, a), dist) * 1e6, label=f"{np.degrees(a):.0f}°"
        )
    axes[1].set_xlabel("distance from the camera [m]")
    axes[1].set_title("σ against distance")
    axes[2].bar(np.arange(noise.led_ids.size), noise.led_level, color="C0")
    axes[2].axhline(1.0, color="k", lw=0.8)
    axes[2].set_xticks(
        np.arange(noise.led_ids.size), [str(int(i)) for i in noise.led_ids], fontsize=7
    )
    axes[2].set_xlabel("LED")
    axes[2].set_ylabel("variance level")
    axes[2].set_title("each LED's level")
    for ax in axes[:2]:
        ax.set_ylabel("noise σ per axis [µm]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(
        f"Noise of the recording (pair second differences, n = {noise.n_samples}, "
        f"level ±{100 * noise.level_rel_se:.1f} %)"
    )
    return _save(fig, path)


def map_figure(path, maps: dict, title: str) -> Path:
    """Joint angle error maps: per joint, the fitted map [mrad] over the joint angle [rad]
    where the data are, with its ±1σ posterior band; `maps` as `map_report`'s
    ``"maps"`` ({joint: {"knots_rad", "value_rad", "sigma_rad", "range_rad"}})."""
    joints = sorted(maps)
    cols = min(3, len(joints))
    rows = -(-len(joints) // cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(4.6 * cols, 3.0 * rows), constrained_layout=True, squeeze=False
    )
    for ax, j in zip(axes.ravel(), joints):
        m = maps[j]
        q = np.asarray(m["knots_rad"])
        v = np.asarray(m["value_rad"]) * 1e3
        s = np.asarray(m["sigma_rad"], float) * 1e3
        ax.fill_between(q, v - s, v + s, color="C0", alpha=0.3, lw=0, label="±1σ")
        ax.plot(q, v, color="C0", lw=1.2, label="map")
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_xlabel(f"q{j} [rad]")
        ax.set_ylabel("angle error [mrad]")
        ax.set_title(f"joint {j}")
    for ax in axes.ravel()[len(joints) :]:
        ax.set_visible(False)
    axes.ravel()[0].legend(fontsize=8)
    fig.suptitle(title)
    return _save(fig, path)
