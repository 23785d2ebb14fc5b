"""Frame-sharded inputs (a 1-D mesh over frames, 2 host devices) give the same results
as unsharded ones, through the chunked and blocked paths of the kernels."""

import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import os
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    import numpy as np
    import jax
    import jax.numpy as jnp
    from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
    import robtraj  # noqa: F401  (enables x64)
    from robtraj.jax_ops import _led_variance, _procrustes, led_variance, weighted_procrustes

    # small chunks and blocks, so the chunked/blocked paths (halos, padding) are sharded
    _led_variance._CHUNK = 32
    _procrustes._BLOCK = 64

    assert len(jax.devices()) == 2, jax.devices()
    mesh = Mesh(np.array(jax.devices()), ("frames",))
    rng = np.random.default_rng(0)
    n, m = 202, 6  # not a multiple of the block or of the device count
    model = 0.1 * rng.normal(size=(m, 3))
    pos = model[None] + 1.0 + 2e-5 * rng.normal(size=(n, m, 3))
    pos[rng.uniform(size=(n, m)) < 0.3] = np.nan
    w = np.where(np.isfinite(pos[..., 0]), rng.uniform(0.5, 2, size=(n, m)), 0.0)
    shard = lambda x: jax.device_put(jnp.asarray(x), NamedSharding(mesh, P("frames")))
    xs = shard(pos)
    assert len(xs.sharding.device_set) == 2
    for variant in ("paper", "pairwise"):
        a = np.asarray(led_variance(jnp.asarray(pos), 9, variant=variant))
        b = np.asarray(led_variance(xs, 9, variant=variant))
        np.testing.assert_array_equal(a, b)  # exactly equal (NaN pattern included)
    fa = weighted_procrustes(jnp.asarray(model), jnp.asarray(pos), jnp.asarray(w))
    fb = weighted_procrustes(jnp.asarray(model), xs, shard(w))
    np.testing.assert_array_equal(np.asarray(fa.valid), np.asarray(fb.valid))
    np.testing.assert_array_equal(np.asarray(fa.n_used), np.asarray(fb.n_used))
    for name in ("quaternion_wxyz", "position", "rms"):
        np.testing.assert_allclose(
            np.asarray(getattr(fa, name)), np.asarray(getattr(fb, name)), rtol=1e-12, atol=1e-15
        )
    print("SHARDING-OK")
    """
)


def test_frame_sharded_matches_unsharded():
    env = dict(
        os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu"
    )
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "SHARDING-OK" in proc.stdout
