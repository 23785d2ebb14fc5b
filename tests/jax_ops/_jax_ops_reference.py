"""Slow, direct NumPy references (loops) and data generators for the kernel tests."""

import numpy as np
from scipy.spatial.transform import Rotation


def led_variance_paper_loop(positions, window, min_count):
    """Paper eq. 3-5 literally: loops over frames, LEDs and window frames."""
    n, m, _ = positions.shape
    h = window // 2
    seen = np.all(np.isfinite(positions), axis=-1)
    # Extended precision for the sums, so the reference is not limited by the rounding
    # of d_t (~eps·|d|, comparable to µm noise variance at the 1e-12 level).
    d = np.full((n, m), np.nan, dtype=np.longdouble)
    for t in range(n):
        for a in range(m):
            if not seen[t, a]:
                continue
            partners = [b for b in range(m) if b != a and seen[t, b]]
            if partners:
                dists = [np.linalg.norm(positions[t, a] - positions[t, b]) for b in partners]
                d[t, a] = sum(np.longdouble(x) for x in dists)
    out = np.full((n, m), np.nan)
    for s in range(n):
        for a in range(m):
            if not seen[s, a]:
                continue
            vals = [
                d[t, a] for t in range(max(0, s - h), min(n, s + h + 1)) if np.isfinite(d[t, a])
            ]
            if len(vals) >= min_count:
                vals = np.array(vals, dtype=np.longdouble)
                out[s, a] = np.mean((vals - vals.mean()) ** 2)
    return out


def led_variance_pairwise_loop(positions, window, min_count):
    n, m, _ = positions.shape
    h = window // 2
    seen = np.all(np.isfinite(positions), axis=-1)
    out = np.full((n, m), np.nan)
    for s in range(n):
        for a in range(m):
            if not seen[s, a]:
                continue
            vs = []
            for b in range(m):
                if b == a:
                    continue
                vals = [
                    np.linalg.norm(positions[t, a] - positions[t, b])
                    for t in range(max(0, s - h), min(n, s + h + 1))
                    if seen[t, a] and seen[t, b]
                ]
                if len(vals) >= min_count:
                    vals = np.array(vals)
                    vs.append(np.mean((vals - vals.mean()) ** 2))
            if vs:
                out[s, a] = np.mean(vs)
    return out


def tool_recording(n, m, *, noise=15e-6, occlusion=0.3, seed=0, radius=0.1):
    """LEDs on a hemisphere of `radius` [m] moving rigidly, Gaussian noise, random occlusion.

    Occlusion comes in runs (LEDs drop out for stretches of frames), like a real tracker.
    """
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(m, 3))
    direction[:, 2] = np.abs(direction[:, 2])
    constellation = radius * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    angles = np.cumsum(rng.normal(scale=0.01, size=(n, 3)), axis=0)
    rot = Rotation.from_rotvec(angles)
    trans = np.array([1.5, 0.2, 0.8]) + np.cumsum(rng.normal(scale=1e-3, size=(n, 3)), axis=0)
    pos = np.einsum("nij,mj->nmi", rot.as_matrix(), constellation) + trans[:, None, :]
    pos = pos + rng.normal(scale=noise, size=pos.shape)
    if occlusion > 0:
        hidden = np.zeros((n, m), bool)
        for a in range(m):
            t = 0
            while t < n:
                run = int(rng.geometric(0.1))
                if rng.uniform() < occlusion:
                    hidden[t : t + run, a] = True
                t += run
        pos[hidden] = np.nan
    return pos, constellation, rot, trans


# ------------------------------------------------- eigen-solver reference for Procrustes


def procrustes_eigh_reference(model, measured, weights):
    """Weighted Horn fit per frame with a dense 4x4 eigen-solver (the former kernel).

    Returns numpy arrays (quaternion_wxyz with w >= 0, position, rms, n_used) for frames
    with at least 3 used LEDs; NaN elsewhere. Independent of the closed-form kernel: no
    quartic, no adjugate.
    """
    model = np.broadcast_to(model, measured.shape)
    n = measured.shape[0]
    quat = np.full((n, 4), np.nan)
    pos = np.full((n, 3), np.nan)
    rms = np.full(n, np.nan)
    used_all = (weights > 0) & np.all(np.isfinite(measured), -1) & np.all(np.isfinite(model), -1)
    for i in range(n):
        used = used_all[i]
        if used.sum() < 3:
            continue
        w = weights[i, used] / weights[i, used].sum()
        p, y = model[i, used], measured[i, used]
        p_bar, y_bar = w @ p, w @ y
        s = np.einsum("k,ki,kj->ij", w, p - p_bar, y - y_bar)
        (sxx, sxy, sxz), (syx, syy, syz), (szx, szy, szz) = s
        horn = np.array(
            [
                [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
                [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
                [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
                [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
            ]
        )
        q = np.linalg.eigh(horn)[1][:, -1]
        q = -q if q[0] < 0 else q
        r = Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix()
        quat[i], pos[i] = q, y_bar - r @ p_bar
        res = y - (p @ r.T + pos[i])
        rms[i] = np.sqrt(w @ np.sum(res * res, -1))
    return quat, pos, rms, used_all.sum(1)
