"""The XLA compiler flag robtraj sets at import: only where jaxlib registers it (XLA aborts
the process on a flag it does not know), never over the user's own setting."""

import os
import subprocess
import sys

import pytest

from robtraj import _xla_flags
from robtraj._xla_flags import ENV, FLAG, jaxlib_knows, set_compile_flags


def test_a_flag_jaxlib_does_not_register_is_not_known():
    assert not jaxlib_knows("xla_cpu_no_such_flag_anywhere")
    assert jaxlib_knows("xla_dump_to")  # one of XLA's oldest flags


def test_the_users_setting_and_the_opt_out_are_kept(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", f"--{FLAG}=true --xla_dump_to=/tmp/x")
    assert not set_compile_flags()
    assert os.environ["XLA_FLAGS"] == f"--{FLAG}=true --xla_dump_to=/tmp/x"
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/x")
    monkeypatch.setenv(ENV, "off")
    assert not set_compile_flags()
    assert os.environ["XLA_FLAGS"] == "--xla_dump_to=/tmp/x"


def test_the_flag_is_added_only_where_jaxlib_knows_it(monkeypatch):
    monkeypatch.delenv(ENV, raising=False)
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/x")
    monkeypatch.setattr(_xla_flags, "jaxlib_knows", lambda flag: False)
    assert not set_compile_flags()
    assert os.environ["XLA_FLAGS"] == "--xla_dump_to=/tmp/x"
    monkeypatch.setattr(_xla_flags, "jaxlib_knows", lambda flag: True)
    assert set_compile_flags()
    assert os.environ["XLA_FLAGS"] == f"--xla_dump_to=/tmp/x --{FLAG}=false"


@pytest.mark.skipif(not jaxlib_knows(FLAG), reason="this jaxlib has no such flag")
def test_a_process_that_imports_robtraj_computes_with_the_flag():
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", ENV)}
    code = "import os, robtraj, jax.numpy as jnp; print(os.environ['XLA_FLAGS'], jnp.ones(3).sum())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == [f"--{FLAG}=false", "3.0"]
