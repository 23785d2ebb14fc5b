"""Where the gap lives: the ranking of variables by the fraction of the held-out gap a
smooth function of each alone removes (`robtraj.analysis._localisation`,
`robtraj.analysis.discrepancy.where_gap_lives`).

The core against a direct NumPy least-squares reference on synthetic arrays; the
channels against finite differences of the public forward model; on simulated
recordings (the `workspace` scenario, 24 s at 25 Hz, as in test_discovery.py) with an
effect that no library effect and no dictionary term is (a joint's angle error as a
function of another joint's angle, or a displacement of the tracker along a fixed
direction drifting with time), the right variable is ranked first; with nothing
hidden, no variable claims a fraction of the gap. One recording per family runs in CI;
the matrices (20 seeds × two magnitudes per family, right first in ≥ 90 %; 40 seeds of
nothing hidden, no claim in ≥ 95 %) are marked `exhaustive` (about a minute):
``pytest -m exhaustive tests/analysis/test_localisation.py``.
"""

import dataclasses

import numpy as np
import pytest

from robtraj.analysis._localisation import KNOTS, basis, heldout_fraction, moments
from robtraj.analysis.discrepancy import Localisation, where_gap_lives
from robtraj.sim import CrossJointError, simulate

# ----------------------------------------------------------------------------- the core


def _synthetic(seed=0, frames=160, leds=4, c=4, g=2, blocks=8, categorical=False):
    """Residuals that are a function of a frame variable along random channels, plus a
    global nuisance displacement and noise; per-observation weights, 3σ² and occlusion."""
    rng = np.random.default_rng(seed)
    channels = rng.normal(size=(frames, leds, 3, c))
    nuisance = rng.normal(size=(frames, leds, 3, g))
    if categorical:
        v = rng.integers(0, 5, frames).astype(float)
        f = np.array([0.0, 1.0, -1.0, 0.5, 2.0])[v.astype(int)]
    else:
        v = rng.uniform(-1.0, 2.0, frames)
        f = np.sin(3 * v)
    sigma = rng.uniform(0.5, 1.5, (frames, leds))
    r = (
        f[:, None, None] * channels[..., 1]
        + 0.3 * nuisance @ rng.normal(size=g)
        + sigma[..., None] * rng.normal(size=(frames, leds, 3))
    )
    seen = rng.uniform(size=(frames, leds)) > 0.2
    r[~seen] = np.nan
    block = np.arange(frames) * blocks // frames
    return r, 1.0 / sigma**2, 3.0 * sigma**2, channels, nuisance, block, v


def _hats(v, categorical, knots=KNOTS):
    """The basis by its definition: an indicator per value, or the piecewise-linear
    interpolation of each unit vector on the knots (np.interp)."""
    if categorical:
        return (v[:, None] == np.unique(v)[None, :]).astype(float)
    t = np.unique(np.quantile(v, np.linspace(0, 1, knots)))
    return np.stack([np.interp(v, t, np.eye(t.size)[k]) for k in range(t.size)], 1)


def _reference(r, w, var3, channels, nuisance, block, v, groups, floor2, categorical):
    """The fraction and its jackknife σ by explicit design matrices and np.linalg.lstsq:
    per fold, the weighted fits of the nuisance alone and of the nuisance with each
    group's function on the training frames (the one of best AIC, or none), their
    predictions on the held-out frames, and the ratio of block sums."""
    frames, leds, _, c = channels.shape
    g = nuisance.shape[-1]
    bas = _hats(v, categorical)
    k = bas.shape[1]
    use = np.isfinite(r[..., 0])
    fi, li = np.nonzero(use)
    design = np.concatenate(
        [
            nuisance[fi, li],
            (channels[fi, li][..., None] * bas[fi][:, None, None, :]).reshape(-1, 3, c * k),
        ],
        -1,
    )  # (n, 3, g + c·k)
    y, sw = r[fi, li], np.sqrt(w[fi, li])
    fold = block[fi] % 2
    gain, gain0 = np.zeros(fi.size), np.zeros(fi.size)
    groups = [tuple(range(c))] if groups is None else groups
    for f in (0, 1):
        tr, he = fold != f, fold == f

        def lsq(cols):
            a = (design[tr][:, :, cols] * sw[tr, None, None]).reshape(-1, len(cols))
            b = (y[tr] * sw[tr, None]).ravel()
            x = np.linalg.lstsq(a, b, rcond=None)[0]
            return x, np.sum((b - a @ x) ** 2)

        x0, chi0 = lsq(list(range(g)))
        best, coef, cols = 0.0, x0, list(range(g))
        for grp in groups:
            gc = list(range(g)) + [g + ch * k + kk for ch in grp for kk in range(k)]
            x, chi = lsq(gc)
            aic = chi0 - chi - 2 * (len(gc) - g)
            if aic > best:
                best, coef, cols = aic, x, gc
        pred = design[he][:, :, cols] @ coef
        pred0 = design[he][:, :, :g] @ x0
        gain[he] = np.sum(y[he] ** 2, -1) - np.sum((y[he] - pred) ** 2, -1)
        gain0[he] = np.sum(y[he] ** 2, -1) - np.sum((y[he] - pred0) ** 2, -1)
    excess = np.sum(y**2, -1) - var3[fi, li]
    sums = [np.bincount(block[fi], x) for x in (gain - gain0, excess - gain0, np.ones(fi.size))]

    def ratio(a, d, n):
        return a / max(d, n * floor2)

    whole = ratio(*(s.sum() for s in sums))
    jack = np.array([ratio(*(s.sum() - s[b] for s in sums)) for b in range(sums[0].size)])
    n = jack.size
    return whole, np.sqrt((n - 1) / n * np.sum((jack - jack.mean()) ** 2))


@pytest.mark.parametrize(
    "groups, categorical, floor2",
    [
        (None, False, 0.0),
        ([(0, 2), (1,), (3,)], False, 0.0),
        ([(0,), (2, 3)], False, 0.0),  # the channel of the function in no group
        (None, True, 0.0),
        (None, False, 50.0),  # the gap² below the floor²: the floor² is the denominator
    ],
)
def test_the_fraction_and_its_jackknife_match_a_least_squares_reference(
    groups, categorical, floor2
):
    r, w, var3, channels, nuisance, block, v = _synthetic(categorical=categorical)
    mom = moments(r, w, var3, channels, nuisance, block, 8)
    got = heldout_fraction(mom, basis(v), groups, floor2)
    want = _reference(r, w, var3, channels, nuisance, block, v, groups, floor2, categorical)
    np.testing.assert_allclose(got, want, rtol=1e-8)
    if groups is None and floor2 == 0:
        assert got[0] > 0.5  # the function along channel 1 is found


def test_a_variable_of_the_frame_gives_the_same_fraction_by_frame_and_by_observation():
    """Units are frames or observations: the same sums, the same fraction."""
    r, w, var3, channels, nuisance, block, v = _synthetic(seed=1)
    frames, leds = w.shape
    by_frame = heldout_fraction(moments(r, w, var3, channels, nuisance, block, 8), basis(v))
    seen = np.isfinite(r[..., 0]).ravel()

    def obs(x):
        return x.reshape(frames * leds, 1, *x.shape[2:])[seen]

    mom = moments(
        obs(r), obs(w), obs(var3), obs(channels), obs(nuisance), np.repeat(block, leds)[seen], 8
    )
    values = np.repeat(v, leds)[seen]
    # the same knots: quantiles of the frames' values
    t = np.unique(np.quantile(v, np.linspace(0, 1, KNOTS)))
    b = basis(values)
    k = np.clip(np.searchsorted(t, values, side="right") - 1, 0, t.size - 2)
    hi = np.clip((values - t[k]) / (t[k + 1] - t[k]), 0, 1)
    b = dataclasses.replace(b, first=k, second=k + 1, a_first=1 - hi, a_second=hi)
    np.testing.assert_allclose(heldout_fraction(mom, b), by_frame, rtol=1e-9)


def test_pure_noise_leaves_no_fraction():
    """No function in the residual: the held-out fraction is not above zero (the
    function fitted to noise does not generalise, or AIC leaves it out)."""
    rng = np.random.default_rng(3)
    r, w, var3, channels, nuisance, block, v = _synthetic(seed=3)
    noise = rng.normal(size=r.shape) * np.sqrt(var3 / 3)[..., None]
    noise[~np.isfinite(r)] = np.nan
    floor2 = 2 * np.sqrt(6 / np.isfinite(r[..., 0]).sum()) * np.mean(var3) / 3
    mom = moments(noise, w, var3, channels, nuisance, block, 8)
    f, s = heldout_fraction(mom, basis(v), None, floor2)
    assert f <= max(2 * s, 0.05), (f, s)


def test_a_variable_with_one_value_has_no_basis():
    assert basis(np.full(10, 2.0)) is None
    assert basis(np.array([np.nan, 1.0, np.nan])) is None
    assert basis(np.array([0.0, 1.0, 0.0, np.nan])).size == 2  # categorical


def test_the_words_name_the_top_variable_with_its_fraction_and_the_next():
    loc = Localisation((("joint 2", 0.78, 0.04), ("time", 0.12, 0.05)), 80e-6, 20e-6, 600)
    assert loc.words("the gap left") == (
        "the gap left lives mostly against joint 2 angle: a smooth function of it alone "
        "removes 78 ± 4 % of the held-out gap (next: time 12 ± 5 %)"
    )
    assert loc.localised == ["joint 2", "time"]
    weak = Localisation((("LED", 0.05, 0.04),), 80e-6, 20e-6, 600)
    assert weak.words().startswith("the gap is not localised by any one variable")
    assert weak.localised == []
    assert "within its floor" in Localisation((), 10e-6, 20e-6, 600).words()
    doc = loc.to_json()
    assert doc["ranking"][0] == {"variable": "joint 2", "fraction": 0.78, "sigma": 0.04}


# ----------------------------------------------------------------------------- recordings


def _recording(seed, unmodelled=(), drift=0.0):
    """The `workspace` scenario, 24 s at 25 Hz; `drift` [m]: every LED measured that much
    times sin(2π t/T) off along a fixed direction of the camera (a mount that sways over
    the recording, not linear in time or temperature as `thermal_drift` is)."""
    rec = simulate("workspace", seed=seed, duration=24.0, rate=25.0, unmodelled=unmodelled)
    if drift:
        sway = drift * np.sin(2 * np.pi * rec.time / rec.time[-1])
        rec = rec.replace(positions=rec.positions + sway[:, None, None] * np.array([0, 0.6, 0.8]))
    return rec.replace(truth=None)


#: family → (its recording at magnitude a for a seed, the magnitudes, the right variables)
FAMILIES = {
    # 1e-4 rad of joint 2 is 0.1 mm at the TCP, about 1 m from its axis
    "joint 2 angle error ∝ sin(6·q1)": (
        lambda a, s: _recording(s, (CrossJointError(2, a, (("sin", 6.0, 1),)),)),
        (1e-4, 3e-4),
        {"joint 1"},
    ),
    # joint 5 is about 0.2 m from the TCP: 5e-4 rad is 0.1 mm
    "joint 5 angle error ∝ sin(2·q1)": (
        lambda a, s: _recording(s, (CrossJointError(5, a, (("sin", 2.0, 1),)),)),
        (5e-4, 1e-3),
        {"joint 1"},
    ),
    # the simulator's camera temperature is a ramp in time: the same variable
    "a displacement in a fixed direction ∝ sin(2π t/T)": (
        lambda a, s: _recording(s, drift=a),
        (1e-4, 3e-4),
        {"time", "temperature"},
    ),
}
#: the seed each family runs with in CI
CI_SEED = 3


def _first(loc) -> str:
    return loc.ranking[0][0]


@pytest.fixture(scope="module")
def nominal():
    """A recording with a joint-2 error as a function of q1 and the nominal fit the
    search starts from."""
    from robtraj.analysis._discovery_state import observations, start

    rec = FAMILIES["joint 2 angle error ∝ sin(6·q1)"][0](3e-4, CI_SEED)
    obs = observations(rec)
    search, _ = start(obs, (), (), None, lambda _m: None)
    return rec, search.nominal


def test_the_channels_are_the_forward_models_first_order_changes(nominal):
    """Each joint's channel is the change of the prediction per radian of its
    `joint_offset`, and a change of flange←tool moves the prediction within the span of
    the nuisance directions (central differences of the public
    `robtraj.estimate.calibration.predict_residuals`)."""
    import jaxlie

    from robtraj.analysis._gap_localisation import joint_sensitivities, nuisance_directions
    from robtraj.analysis._residual_stats import aligned
    from robtraj.estimate.calibration import predict_residuals
    from robtraj.recording import Pose

    rec, cal = nominal
    frames = np.arange(rec.n_frames)
    positions = aligned(rec, cal, np.asarray(rec.positions)) - cal.residuals  # the model's
    sens, camera_from_tool = joint_sensitivities(rec, cal, frames, positions)
    step = 1e-5

    def change(moved):
        """d(prediction)/d(step) = −d(residual)/d(step), central."""
        plus, minus = (predict_residuals(rec, moved(s), ("joint_offset",)) for s in (step, -step))
        return (minus - plus) / (2 * step)

    for j in (0, 1, 4):
        d = change(
            lambda s, j=j: dataclasses.replace(
                cal, effects={**cal.effects, "joint_offset": s * np.eye(6)[j]}
            )
        )
        ok = np.isfinite(d[..., 0])
        scale = np.abs(sens[..., j, :][ok]).max()
        np.testing.assert_allclose(d[ok], sens[..., j, :][ok], atol=1e-4 * scale)

    xi = np.array([1.0, -2.0, 0.5, 3.0, 1.0, -2.0])  # tool frame: [m, m, m, rad, rad, rad]
    ft = jaxlie.SE3(
        np.concatenate([cal.flange_from_tool.quaternion_wxyz, cal.flange_from_tool.position])
    )

    def tool_moved(s):
        return dataclasses.replace(
            cal, flange_from_tool=Pose.from_wxyz_xyz((ft @ jaxlie.SE3.exp(s * xi)).wxyz_xyz)
        )

    d = change(tool_moved)
    ok = np.isfinite(d[..., 0])
    n = nuisance_directions(positions, camera_from_tool)[ok].reshape(-1, 12)
    coef, *_ = np.linalg.lstsq(n, d[ok].ravel(), rcond=None)
    assert np.linalg.norm(n @ coef - d[ok].ravel()) < 1e-4 * np.linalg.norm(d[ok])
    np.testing.assert_allclose(coef[6:], xi, rtol=1e-3)  # the tool's own directions


@pytest.mark.parametrize("family", list(FAMILIES))
def test_the_variable_of_a_hidden_effect_is_ranked_first(family):
    """CI: one seed per family at the smaller magnitude: the variable of the hidden
    effect first, with most of the held-out gap, more than 2σ above zero."""
    make, (small, _), right = FAMILIES[family]
    loc = where_gap_lives(make(small, CI_SEED))
    assert loc.gap_m > loc.floor_m
    top, f, s = loc.ranking[0]
    assert top in right, loc.ranking[:3]
    assert f > 0.5 and f > 2 * s, loc.ranking[:3]


@pytest.mark.exhaustive
@pytest.mark.parametrize("magnitude", [0, 1])
@pytest.mark.parametrize("family", list(FAMILIES))
def test_the_right_variable_first_in_90_percent_of_seeds(family, magnitude):
    """The variable of the hidden effect ranked first in ≥ 90 % of 20 seeds (at most two
    failures), at 0.1 and 0.2–0.3 mm at the TCP (measured: 18, 19, 18, 20, 20 and 20 of
    20; a seed can fail where the poses of one fold do not cover the other fold's values
    of the variable)."""
    make, magnitudes, right = FAMILIES[family]
    firsts = [_first(where_gap_lives(make(magnitudes[magnitude], s))) for s in range(20)]
    bad = [(s, v) for s, v in enumerate(firsts) if v not in right]
    assert len(bad) <= 2, bad


def _null_claims(seed):
    """The variables of a recording with nothing hidden that claim a fraction of the
    nominal gap: more than 2σ and more than 5 % above zero."""
    loc = where_gap_lives(_recording(seed))
    return [(v, f, s) for v, f, s in loc.ranking if f > max(2 * s, 0.05)]


@pytest.mark.parametrize(
    "seeds, allowed", [(1, 0), pytest.param(40, 2, marks=pytest.mark.exhaustive)]
)
def test_with_nothing_hidden_no_variable_claims_the_gap(seeds, allowed):
    """Nothing hidden: every variable's fraction is within 2σ of zero or below 5 % in
    ≥ 95 % of seeds (1 in CI, 40 on demand)."""
    claims = {s: c for s in range(seeds) if (c := _null_claims(s))}
    assert len(claims) <= allowed, claims
