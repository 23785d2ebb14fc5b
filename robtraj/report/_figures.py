"""Report figures: arrays in, one legible PNG out (matplotlib, Agg). SI in, mm/µm/° on axes."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

_DPI = 110


#: time bins of the visibility image beyond which frames are shown as a fraction seen
IMAGE_COLUMNS = 2000
#: runs of frames a per-frame curve is drawn with: beyond twice as many frames, each run's
#: smallest and largest value (far more runs than the figure has pixel columns)
FIGURE_RUNS = 20_000
IMAGE_CHUNK = 1 << 16  # frames compared at a time (bounded temporaries on long recordings)


def envelope(values: np.ndarray, runs: int = FIGURE_RUNS) -> np.ndarray:
    """Indices of the frames a figure draws of the per-frame series `values` `(N,)`: all
    of them up to ``2 * runs`` frames; else, in each of `runs` equal runs of consecutive
    frames, the first frame with the run's smallest and the first with its largest finite
    value (every extreme is kept, so spikes show; a run without one is left out)."""
    n = np.shape(values)[0]
    if n <= 2 * runs:
        return np.arange(n)
    edges = np.linspace(0, n, runs + 1).astype(np.int64)
    keep = []
    # a group of runs at a time: the temporaries stay small on long recordings
    group = max(1, IMAGE_CHUNK // int(np.diff(edges).max()))
    for g in range(0, runs, group):
        e = edges[g : g + group + 1]
        v = np.asarray(values[e[0] : e[-1]], float)
        run = np.repeat(np.arange(e.size - 1), np.diff(e))
        finite = np.isfinite(v)
        for fill, reduce in ((np.inf, np.minimum), (-np.inf, np.maximum)):
            extreme = reduce.reduceat(np.where(finite, v, fill), e[:-1] - e[0])
            at = np.flatnonzero(finite & (v == extreme[run]))
            keep.append(e[0] + at[np.unique(run[at], return_index=True)[1]])
    return np.unique(np.concatenate(keep))


def _save(fig, path: str | os.PathLike) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=_DPI, format="png")
    plt.close(fig)
    return path


def path_3d_figure(
    path: str | os.PathLike,
    position: np.ndarray,
    distance: np.ndarray,
    *,
    reference: np.ndarray | None = None,
    title: str = "Measured TCP path, coloured by deviation from the commanded path",
) -> Path:
    """3D measured path `(N, 3)` [m] coloured by its deviation `(N,)` [m] (shown in mm),
    with the commanded path `reference` `(R, 3)` [m] drawn over it (red, dashed), and a
    top view (x–y) beside it where the two are easier to tell apart."""
    fig = plt.figure(figsize=(12, 5.6), layout="constrained")
    fig.get_layout_engine().set(wspace=0.12)
    ax = fig.add_subplot(1, 2, 1, projection="3d", computed_zorder=False)
    top = fig.add_subplot(1, 2, 2)
    rows = np.flatnonzero(np.all(np.isfinite(position), axis=1) & np.isfinite(distance))
    d = distance[rows] * 1e3
    vmax, n_above = robust_limit(d)
    drawn = envelope(d)
    p, d = position[rows[drawn]] * 1e3, d[drawn]
    kw = dict(c=d, s=2, cmap="viridis", vmin=0.0, vmax=vmax, zorder=1, label="measured")
    sc = ax.scatter(*p.T, **kw)
    top.scatter(p[:, 0], p[:, 1], **kw)
    if reference is not None:
        r = np.asarray(reference) * 1e3
        style = dict(color="C3", lw=1.4, ls="--", zorder=10, label="commanded")
        ax.plot(*r.T, **style)
        top.plot(r[:, 0], r[:, 1], **style)
        top.legend(loc="best", markerscale=4)
    fig.colorbar(sc, ax=[ax, top], shrink=0.8, extend="max" if n_above else "neither",
                 label="deviation [mm]" + (f" ({n_above} frames above the scale)" if n_above else ""))  # fmt: skip
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")
    top.set_xlabel("x [mm]")
    top.set_ylabel("y [mm]")
    top.set_aspect("equal", adjustable="datalim")
    top.grid(True, alpha=0.3)
    top.set_title("top view")
    fig.suptitle(title)
    return _save(fig, path)


def deviation_figure(
    path: str | os.PathLike,
    progress: np.ndarray,
    distance: np.ndarray,
    orientation_error: np.ndarray,
    *,
    on_path: np.ndarray | None = None,
    title: str = "Deviation from the commanded path",
) -> Path:
    """Distance [m → mm] and orientation error [rad → °] against path progress [m → mm];
    frames off the path (joint moves, `on_path` False) in grey."""
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(10, 6), sharex=True, constrained_layout=True)
    use = np.ones(np.shape(progress), bool) if on_path is None else np.asarray(on_path, bool)
    for ax, v, unit, label in [
        (a0, distance, 1e3, "distance [mm]"),
        (a1, orientation_error, np.degrees(1.0), "orientation error [°]"),
    ]:
        for part, style in ((~use, dict(color="0.7", label="joint moves")),
                            (use, dict(color="C0", label="path"))):  # fmt: skip
            rows = np.flatnonzero(part)
            i = rows[envelope(v[rows])]
            ax.plot(progress[i] * 1e3, v[i] * unit, ".", ms=1, **style)
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    a0.set_title(title)
    a1.set_xlabel("path progress s [mm]")
    if not use.all():
        a0.legend(markerscale=8)
    return _save(fig, path)


def velocity_figure(
    path: str | os.PathLike,
    time: np.ndarray,
    speed: np.ndarray,
    *,
    commanded: np.ndarray | None = None,
    title: str = "TCP speed",
) -> Path:
    """Measured TCP speed `(N,)` [m/s → mm/s] over time [s], with the commanded speed."""
    fig, ax = plt.subplots(figsize=(10, 4), constrained_layout=True)
    t = time - time[0]
    i = envelope(speed)
    ax.plot(t[i], speed[i] * 1e3, lw=0.7, label="measured")
    if commanded is not None:
        ax.plot(t, np.asarray(commanded) * 1e3, lw=1.0, ls="--", color="C3", label="commanded")
        ax.legend()
    ax.set_xlabel("time [s]")
    ax.set_ylabel("speed [mm/s]")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    return _save(fig, path)


def visibility_figure(
    path: str | os.PathLike,
    time: np.ndarray,
    visible: np.ndarray,
    *,
    led_ids: np.ndarray | None = None,
    variance: np.ndarray | None = None,
    title: str = "LEDs seen by the camera (black) over time",
) -> Path:
    """Paper Fig. 3: visibility image `(N, M)` (LED vs time; longer recordings shown as
    the fraction of frames seen in each of `IMAGE_COLUMNS` time bins) and, if given, the
    LED variance [m²] of the three LEDs whose visibility changes most (`most_changing`),
    as a std in µm, on an axis clipped by `robust_limit` (values above it drawn at the
    limit and marked). `variance` is `(N, M)`, or `(N, 3)` for those three LEDs in that
    order."""
    t = time - time[0]
    m = visible.shape[1]
    ids = np.arange(m) if led_ids is None else np.asarray(led_ids)
    rows = 2 if variance is not None else 1
    fig, axes = plt.subplots(rows, 1, figsize=(10, 3.5 * rows), sharex=True,
                             constrained_layout=True, squeeze=False)  # fmt: skip
    a0 = axes[0, 0]
    a0.imshow(_binned(visible).T, aspect="auto", interpolation="nearest",
              cmap="Greys", vmin=0, vmax=1, extent=(t[0], t[-1], m + 0.5, 0.5))  # fmt: skip
    step = max(1, m // 24)
    a0.set_yticks(np.arange(1, m + 1)[::step], [str(i) for i in ids[::step]], fontsize=7)
    a0.set_ylabel("LED id")
    a0.set_title(title)
    if variance is not None:
        a1 = axes[1, 0]
        pick = most_changing(visible)
        variance = np.asarray(variance)
        if variance.shape[1] == m:
            variance = variance[:, pick]
        with np.errstate(invalid="ignore"):
            std = np.sqrt(variance)
        std *= 1e6
        top, n_clipped = robust_limit(std)
        for j, k in enumerate(pick):
            i = envelope(std[:, j])
            a1.plot(t[i], np.minimum(std[i, j], top), lw=0.8, label=f"LED {ids[k]}")
        if n_clipped:
            above = std > top
            a1.plot(t[above.any(1)], np.full(above.any(1).sum(), top), "v", color="C3",
                    ms=4, label=f"clipped: {n_clipped} samples, max {np.nanmax(std) / 1e3:.3g} mm")  # fmt: skip
        if np.isfinite(top):
            a1.set_ylim(0, top * 1.05)
        a1.set_ylabel("LED variance, as std [µm]")
        a1.set_title("LED variance (axis clipped at median + 10 robust σ; spikes marked ▼)")
        a1.legend(fontsize=8, loc="upper right")
        a1.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel("time [s]")
    return _save(fig, path)


def most_changing(visible: np.ndarray, k: int = 3) -> np.ndarray:
    """Columns of the `k` LEDs whose visibility `(N, M)` changes most often (ties: the
    most seen first)."""
    n = visible.shape[0]
    changes = np.zeros(visible.shape[1], np.int64)
    for a in range(0, n - 1, IMAGE_CHUNK):
        b = min(a + IMAGE_CHUNK, n - 1)
        changes += np.count_nonzero(visible[a + 1 : b + 1] != visible[a:b], axis=0)
    return np.argsort(-(changes + 1e-3 * np.count_nonzero(visible, axis=0)), kind="stable")[:k]


def _binned(visible: np.ndarray) -> np.ndarray:
    """`visible` `(N, M)` as float, or for more than `IMAGE_COLUMNS` frames the fraction
    of frames seen in each of `IMAGE_COLUMNS` equal time bins `(IMAGE_COLUMNS, M)`."""
    n = visible.shape[0]
    if n <= IMAGE_COLUMNS:
        return np.asarray(visible, float)
    edges = np.linspace(0, n, IMAGE_COLUMNS + 1).astype(np.int64)
    counts = np.empty((IMAGE_COLUMNS, visible.shape[1]), np.int64)
    # bins a group at a time: reduceat casts its whole input to the count's type
    group = max(1, IMAGE_CHUNK // int(np.diff(edges).max()))
    for i in range(0, IMAGE_COLUMNS, group):
        e = edges[i : i + group + 1]
        counts[i : i + e.size - 1] = np.add.reduceat(
            visible[e[0] : e[-1]], e[:-1] - e[0], axis=0, dtype=np.int64
        )
    return counts / np.diff(edges)[:, None]


def robust_limit(values: np.ndarray, k: float = 10.0) -> tuple[float, int]:
    """Axis limit median + `k`·σ̂ of the finite `values`, σ̂ = 1.4826·MAD (the normal
    standard deviation for Gaussian data), so that spikes do not set the scale; and how
    many values lie above it. Falls back to the largest value when the MAD is zero."""
    v = np.asarray(values, float)
    d = v[np.isfinite(v)]  # the one copy: medians partition it in place
    if d.size == 0:
        return float("nan"), 0
    med = float(np.median(d, overwrite_input=True))
    d -= med
    top = med + k * 1.4826 * float(np.median(np.abs(d), overwrite_input=True))
    if top <= 0 or top <= med:
        return float(np.max(d) + med) or 1.0, 0
    return top, int(np.count_nonzero(d > top - med))


def static_pose_figure(
    path: str | os.PathLike,
    position_error: np.ndarray,
    angle_error: np.ndarray,
    *,
    title: str = "Error of each static pose against its command",
) -> Path:
    """Position error `(N,)` [m → mm] and orientation error `(N,)` [rad → °] per pose
    number, with their histograms."""
    fig, axes = plt.subplots(2, 2, figsize=(10, 5.5), width_ratios=(3, 1), sharey="row",
                             layout="constrained")  # fmt: skip
    n = np.arange(1, position_error.shape[0] + 1)
    for row, (v, label) in enumerate(
        [
            (position_error * 1e3, "position error [mm]"),
            (np.degrees(angle_error), "orientation error [°]"),
        ]
    ):
        ok = np.isfinite(v)
        axes[row, 0].plot(n[ok], v[ok], ".", ms=2)
        axes[row, 0].set_ylabel(label)
        axes[row, 1].hist(v[ok], bins=40, orientation="horizontal", color="C1")
        for a in axes[row]:
            a.grid(True, alpha=0.3)
    axes[1, 0].set_xlabel("pose number")
    axes[1, 1].set_xlabel("poses")
    axes[0, 0].set_title(title)
    return _save(fig, path)


def pose_quality_figure(
    path: str | os.PathLike,
    time: np.ndarray,
    rms: np.ndarray,
    n_used: np.ndarray,
    *,
    title: str = "Pose fit quality over time",
) -> Path:
    """Per-frame RMS residual of the pose fit `(N,)` [m → µm] and LEDs used `(N,)`."""
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(10, 5.5), sharex=True, constrained_layout=True)
    t = time - time[0]
    i = envelope(rms)
    a0.plot(t[i], rms[i] * 1e6, lw=0.6)
    a0.set_ylabel("fit RMS [µm]")
    a0.set_title(title)
    i = envelope(n_used)
    a1.step(t[i], n_used[i], where="mid", lw=0.6, color="C2")
    a1.set_ylabel("LEDs used")
    a1.set_xlabel("time [s]")
    for a in (a0, a1):
        a.grid(True, alpha=0.3)
    return _save(fig, path)


def weighting_figure(
    path: str | os.PathLike,
    time: np.ndarray,
    truth_position: np.ndarray,
    estimates: dict[str, np.ndarray],
    *,
    edge: np.ndarray | None = None,
    title: str = "Tool position per weighting scheme near the visibility edge",
) -> Path:
    """Paper Fig. 4 kind: each scheme's position error against truth [m → µm] per axis
    over time [s] (1-frame noise smoothed over 25 frames), with frames where an LED is at
    the edge of visibility (`edge` `(N,)` bool) shaded."""
    t = time - time[0]
    fig, axes = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True, constrained_layout=True)
    kernel = np.ones(25) / 25
    for name, pos in estimates.items():
        err = (pos - truth_position) * 1e6
        for k, ax in enumerate(axes):
            e = np.convolve(np.nan_to_num(err[:, k]), kernel, mode="same")
            ax.plot(t, e, lw=0.8, label=name)
    for k, ax in enumerate(axes):
        if edge is not None:
            ax.fill_between(t, 0, 1, where=edge, transform=ax.get_xaxis_transform(),
                            color="0.85", step="mid", label="LED at visibility edge" if k == 0 else None)  # fmt: skip
        ax.set_ylabel(f"{'xyz'[k]} error [µm]")
        ax.grid(True, alpha=0.3)
    axes[0].set_title(title)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time [s]")
    return _save(fig, path)


def workspace_error_figure(
    path: str | os.PathLike,
    tool_position: np.ndarray,
    position_error: np.ndarray,
    angle_error: np.ndarray,
    *,
    title: str = "Prediction error over the workspace",
) -> Path:
    """Tool positions `(N, 3)` in the base frame [m] seen from above (x–y) and from the
    side (x–z), coloured by the position error `(N,)` [m → mm] and the orientation error
    `(N,)` [rad → °]."""
    fig, axes = plt.subplots(2, 2, figsize=(10, 8), layout="constrained")
    ok = np.all(np.isfinite(tool_position), -1) & np.isfinite(position_error)
    x, y, z = (tool_position[ok, i] for i in range(3))
    for row, (v, label, cmap) in enumerate(
        [
            (position_error[ok] * 1e3, "position error [mm]", "viridis"),
            (np.degrees(angle_error[ok]), "orientation error [°]", "magma"),
        ]
    ):
        for col, (h, name) in enumerate([(y, "y"), (z, "z")]):
            a = axes[row, col]
            sc = a.scatter(x, h, c=v, s=6, cmap=cmap, vmin=0.0, vmax=float(np.quantile(v, 0.99)))
            a.set_xlabel("x (base) [m]")
            a.set_ylabel(f"{name} (base) [m]")
            a.set_aspect("equal", adjustable="datalim")
            a.grid(True, alpha=0.3)
        fig.colorbar(sc, ax=axes[row].tolist(), label=label)
    axes[0, 0].set_title(title)
    return _save(fig, path)


def compensation_figure(
    path: str | os.PathLike,
    names: list[str],
    now: np.ndarray,
    after: np.ndarray,
    sigma: np.ndarray,
) -> Path:
    """AP per test pose `names`: measured now and predicted after compensation `(P,)`
    [m] (shown in µm, log scale), the prediction with its ±2σ `(P,)` [m]."""
    fig, ax = plt.subplots(figsize=(7.5, 4.2), layout="constrained")
    x = np.arange(len(names))
    w = 0.38
    ax.bar(x - w / 2, now * 1e6, w, label="measured now", color="tab:red")
    ax.bar(x + w / 2, after * 1e6, w, label="after compensation (predicted)", color="tab:green")
    ax.errorbar(x + w / 2, after * 1e6, yerr=2 * sigma * 1e6, fmt="none", ecolor="k",
                capsize=4, label="±2σ of the calibration")  # fmt: skip
    ax.set_yscale("log")
    ax.set_xticks(x, names)
    ax.set_ylabel("AP [µm]")
    ax.set_title("Pose accuracy AP: measured and predicted after compensation")
    fig.legend(loc="outside lower center", ncol=3, fontsize=8)
    return _save(fig, path)
