"""led_variance against direct loops of paper eq. 3-5 (and the pairwise variant)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _jax_ops_reference import (
    led_variance_pairwise_loop,
    led_variance_paper_loop,
    tool_recording,
)

from robtraj.jax_ops import led_variance, led_variances, windowed_moments

REFERENCES = {"paper": led_variance_paper_loop, "pairwise": led_variance_pairwise_loop}


def _compare(got, want, rtol):
    got = np.asarray(got)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    ok = np.isfinite(want)
    assert ok.any()
    rel = np.abs(got[ok] - want[ok]) / np.abs(want[ok])
    assert rel.max() < rtol, rel.max()


@pytest.mark.parametrize("variant", ["paper", "pairwise"])
@pytest.mark.parametrize("occlusion", [0.0, 0.3])
@pytest.mark.parametrize("window", [7, 10])
def test_matches_direct_loop_float64(variant, occlusion, window):
    # Realistic: 0.1 m constellation, 15 µm noise. The residual ~1e-12 is the rounding
    # of the distances themselves (1 ulp of 0.1 m against ~20 µm noise), not the kernel.
    pos, *_ = tool_recording(90, 6, occlusion=occlusion, seed=window)
    min_count = max(2, window // 2)
    want = REFERENCES[variant](pos, window, min_count)
    got = led_variance(jnp.asarray(pos), window, variant=variant)
    assert got.dtype == jnp.float64 and got.shape == pos.shape[:2]
    _compare(got, want, rtol=3e-12)


@pytest.mark.parametrize("variant", ["paper", "pairwise"])
def test_window_edges_min_count_and_all_unseen_led(variant):
    pos, *_ = tool_recording(40, 5, occlusion=0.4, seed=11)
    pos[:, 4] = np.nan  # never seen
    pos[10:13] = np.nan  # nothing seen for three frames
    want = REFERENCES[variant](pos, 9, 6)
    got = led_variance(jnp.asarray(pos), 9, variant=variant, min_count=6)
    assert np.all(np.isnan(np.asarray(got)[:, 4]))
    _compare(got, want, rtol=3e-12)


def test_paper_variance_jumps_when_partner_disappears_pairwise_does_not():
    pos, *_ = tool_recording(60, 6, occlusion=0.0, seed=2)
    pos[30:, 5] = np.nan
    paper = np.asarray(led_variance(jnp.asarray(pos), 9, variant="paper"))
    pairwise = np.asarray(led_variance(jnp.asarray(pos), 9, variant="pairwise"))
    assert paper[30, 0] > 1e4 * np.median(paper[:20, 0])
    assert pairwise[30, 0] < 10 * np.median(pairwise[:20, 0])


def test_long_recording_precision_does_not_degrade():
    # Block-local prefix sums: the error does not grow with the number of frames.
    rng = np.random.default_rng(0)
    n = 200_000
    x = 0.7 + 1e-5 * rng.normal(size=(n, 1))
    x[n // 2 :] += 0.15  # a jump, as when a partner appears
    count, mean, m2 = windowed_moments(jnp.asarray(x), jnp.ones((n, 1), bool), 5)
    for s in (3, 1000, n // 2 - 20, n // 2, n - 1):
        vals = x[max(0, s - 5) : s + 6, 0]
        np.testing.assert_allclose(float(m2[s, 0] / count[s, 0]), vals.var(), rtol=1e-11)
        np.testing.assert_allclose(float(mean[s, 0]), vals.mean(), rtol=1e-15)


@pytest.mark.parametrize("variant", ["paper", "pairwise"])
def test_float32(variant):
    pos, *_ = tool_recording(60, 6, occlusion=0.2, seed=5)
    want = REFERENCES[variant](pos, 9, 4)
    # float32 positions near 1.5 m carry ~0.1 µm rounding; relative to ~20 µm noise the
    # variance is good to a few 1e-2 for the paper variant (d_t ~ 0.5 m rounds to 3e-8).
    got = led_variance(jnp.asarray(pos, jnp.float32), 9, variant=variant)
    assert got.dtype == jnp.float32
    got = np.asarray(got, np.float64)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    ok = np.isfinite(want)
    np.testing.assert_allclose(got[ok], want[ok], rtol=0.1)
    assert np.median(np.abs(got[ok] / want[ok] - 1)) < 0.02


def test_gradient_is_finite_with_occlusion():
    pos, *_ = tool_recording(30, 5, occlusion=0.3, seed=7)
    x = jnp.asarray(pos)

    def loss(p):
        v = led_variance(p, 7, variant="pairwise")
        return jnp.sum(jnp.where(jnp.isnan(v), 0.0, v))

    g = np.asarray(jax.grad(loss)(x))
    seen = np.isfinite(pos)
    assert np.all(np.isfinite(g[seen])) and np.all(g[~seen] == 0)


def test_both_variants_in_one_pass_match_each_alone():
    pos, *_ = tool_recording(300, 6, occlusion=0.3, seed=3)
    x = jnp.asarray(pos)
    both = led_variances(x, 9, variants=("pairwise", "paper"))
    for got, variant in zip(both, ("pairwise", "paper")):
        # the same sums, fused differently: equal to rounding
        alone = np.asarray(led_variance(x, 9, variant=variant))
        np.testing.assert_allclose(np.asarray(got), alone, rtol=1e-13, atol=0)


@pytest.mark.parametrize("variant", ["paper", "pairwise"])
def test_gradient_matches_finite_differences(variant):
    pos, *_ = tool_recording(40, 5, occlusion=0.2, seed=11)
    x = jnp.asarray(pos)
    rng = np.random.default_rng(0)
    direction = jnp.asarray(np.where(np.isfinite(pos), rng.normal(size=pos.shape), 0.0))

    def loss(p):
        v = led_variance(p, 7, variant=variant)
        return jnp.sum(jnp.where(jnp.isnan(v), 0.0, v)) * 1e9  # [mm²]-like scale

    g = jax.grad(loss)(x)
    analytic = float(jnp.sum(jnp.where(jnp.isfinite(x), g, 0.0) * direction))
    eps = 1e-7
    fd = (loss(x + eps * direction) - loss(x - eps * direction)) / (2 * eps)
    np.testing.assert_allclose(analytic, float(fd), rtol=1e-5)


def test_bad_input():
    with pytest.raises(ValueError):
        led_variance(jnp.zeros((10, 4, 3)), 0)
    with pytest.raises((ValueError, TypeError)):  # TypeError: jaxtyping's runtime check
        led_variance(jnp.zeros((10, 4, 3)), 5, variant="median")


def test_windowed_range_is_zero_matches_naive():
    from robtraj.jax_ops._windowed import windowed_range_is_zero

    rng = np.random.default_rng(3)
    n, h = 57, 4
    x = np.repeat(rng.integers(0, 3, size=(n // 6 + 1, 3)), 6, axis=0)[:n].astype(float)
    valid = rng.uniform(size=x.shape) < 0.7
    got = np.asarray(windowed_range_is_zero(jnp.asarray(x), jnp.asarray(valid), h))
    for s in range(n):
        for j in range(3):
            vals = x[max(0, s - h) : s + h + 1, j][valid[max(0, s - h) : s + h + 1, j]]
            assert got[s, j] == (len(vals) == 0 or np.all(vals == vals[0]))


@pytest.mark.parametrize("variant", ["paper", "pairwise"])
def test_chunked_with_halo_matches_direct_loop(variant, monkeypatch):
    # Chunks of 16 frames with a halo of 3: windows straddle chunk boundaries, and a
    # partner drops out across one (the paper variant's per-chunk reference distance).
    from robtraj.jax_ops import _led_variance as lv

    monkeypatch.setattr(lv, "_CHUNK", 16)
    pos, *_ = tool_recording(83, 6, occlusion=0.3, seed=31)  # 83 frames: a shape of its own
    pos[40:, 2] = np.nan
    want = REFERENCES[variant](pos, 7, 3)
    got = led_variance(jnp.asarray(pos), 7, variant=variant)
    _compare(got, want, rtol=3e-12)
