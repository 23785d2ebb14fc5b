"""Figures of the paper's kind: LED visibility/variance (Fig. 3), weighting comparison (Fig. 4)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def visibility_figure(rec, est, path: Path) -> Path:
    """LED visibility over time (image) and the LED variance of a few LEDs (paper Fig. 3)."""
    from ..estimate import chunked_led_variance

    t = rec.time - rec.time[0]
    vis = rec.visible
    var = chunked_led_variance(np.asarray(rec.positions), est.window, "paper")
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(10, 7), sharex=True, constrained_layout=True)
    a0.imshow(
        vis.T,
        aspect="auto",
        interpolation="nearest",
        cmap="Greys",
        extent=(t[0], t[-1], rec.n_leds + 0.5, 0.5),
    )
    a0.set_yticks(np.arange(1, rec.n_leds + 1), [str(i) for i in rec.led_ids], fontsize=7)
    a0.set_ylabel("LED id")
    a0.set_title("LEDs seen by the camera (black) over time")
    # the LEDs whose visibility changes most, as in the paper's three-LED view
    changes = np.abs(np.diff(vis.astype(int), axis=0)).sum(0)
    pick = np.argsort(-(changes + 1e-3 * vis.sum(0)))[:3]
    for k in pick:
        a1.semilogy(t, np.sqrt(var[:, k]) * 1e6, lw=0.8, label=f"LED {rec.led_ids[k]}")
    a1.set_xlabel("time [s]")
    a1.set_ylabel("LED variance, as std [µm]")
    a1.set_title(f"LED variance of the summed distances (window {est.window} frames)")
    a1.legend()
    a1.grid(True, which="both", alpha=0.3)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def pose_comparison_figure(rec, results: dict, path: Path) -> Path:
    """Position error against truth over time per weighting scheme (paper Fig. 4 effect)."""
    t = rec.time - rec.time[0]
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(10, 7), sharex=True, constrained_layout=True)
    for name, (est, pe, ae) in results.items():
        a0.plot(t, pe * 1e6, lw=0.6, label=name)
        a1.plot(t, np.degrees(ae) * 1e3, lw=0.6, label=name)
    a0.set_ylabel("position error [µm]")
    a0.set_title("Tool position error against truth per weighting scheme")
    a1.set_ylabel("orientation error [mdeg]")
    a1.set_xlabel("time [s]")
    for a in (a0, a1):
        a.legend()
        a.grid(True, alpha=0.3)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
