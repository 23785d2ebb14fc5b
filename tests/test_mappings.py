"""The process's memory mappings: compiled kernels hold them, `make_room` gives them back
before the kernel's limit (reached, the process dies inside XLA's compiler)."""

import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from robtraj._mappings import make_room, mapping_count, mapping_limit

pytestmark = pytest.mark.skipif(mapping_limit() is None, reason="no /proc (not Linux)")

#: distinct kernels compiled per check
KERNELS = 40


def _compile_kernels(n: int, offset: int) -> list:
    """`n` jitted functions, each compiled for its own shape (kept alive by the list)."""
    fns = []
    for i in range(n):
        f = jax.jit(lambda x, i=i: jnp.sin(x) * i + jnp.cumsum(x))
        f(jnp.ones(offset + i)).block_until_ready()
        fns.append(f)
    return fns


def test_the_count_is_the_lines_of_proc_maps():
    with open("/proc/self/maps") as fh:
        lines = len(fh.readlines())
    assert abs(mapping_count() - lines) <= 2  # the reads themselves may map a page


def test_compiled_kernels_hold_mappings_and_make_room_returns_them():
    before = mapping_count()
    fns = _compile_kernels(KERNELS, 1000)
    held = mapping_count() - before
    # each compiled kernel holds several mappings of its own (code and data sections)
    assert held >= 5 * KERNELS, held
    # with room left under the limit: nothing happens
    assert make_room(0.5, limit=10 * mapping_count()) is None
    assert mapping_count() - before >= held - KERNELS
    # past the fraction of the limit: the caches are cleared and the mappings given back
    said = make_room(0.5, limit=mapping_count())
    assert said is not None and "cleared" in said and "vm.max_map_count" in said
    assert mapping_count() - before < held / 4, (held, mapping_count() - before)
    # a cleared function compiles again and gives the same result
    x = jnp.ones(1003)
    np.testing.assert_array_equal(fns[3](x), jnp.sin(x) * 3 + jnp.cumsum(x))


_LOOP = """
import sys
import jax, jax.numpy as jnp
import robtraj
from robtraj._mappings import make_room, mapping_count, mapping_limit
guard = sys.argv[1] == "guard"
limit, taken, most, fns = mapping_limit(), 0, 0, []
last = mapping_count()
i = 0
while taken < 1.2 * limit:  # the kernels have taken more mappings than the limit
    f = jax.jit(lambda x, i=i: jnp.sin(x) * i + jnp.cumsum(x))
    f(jnp.ones(i + 3)).block_until_ready()
    fns.append(f)
    now = mapping_count()
    taken, most, last = taken + max(0, now - last), max(most, now), now
    if guard and i % 100 == 0:
        make_room()
        last = mapping_count()
    i += 1
print(most, limit)
"""


@pytest.mark.exhaustive
def test_a_process_that_compiles_past_the_limit_survives_with_make_room():
    """Compiling kernels that take 1.2 times the system's mapping limit: the process
    dies inside XLA's compiler (SIGSEGV) without `make_room`, and survives with it called
    every 100 kernels (20 minutes for both on the 2-core machine beside another job)."""
    code = textwrap.dedent(_LOOP)
    guarded = subprocess.run(
        [sys.executable, "-c", code, "guard"], capture_output=True, text=True, timeout=1800
    )
    assert guarded.returncode == 0, guarded.stderr[-2000:]
    most, limit = map(int, guarded.stdout.split())
    assert most < limit
    bare = subprocess.run(
        [sys.executable, "-c", code, "bare"], capture_output=True, text=True, timeout=1800
    )
    assert bare.returncode == -11, (bare.returncode, bare.stderr[-2000:])
