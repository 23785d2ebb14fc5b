"""Figures of the discrepancy workflow: the gap step by step, residual structure."""

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
