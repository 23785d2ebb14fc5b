"""Where the CLI's persistent JAX compilation cache goes, and how it is turned off."""

import sys
from pathlib import Path

import pytest

from robtraj._jax_cache import ENV, compilation_cache_dir


def test_env_var_moves_or_disables_the_cache(monkeypatch, tmp_path):
    monkeypatch.setenv(ENV, str(tmp_path / "c"))
    assert compilation_cache_dir() == tmp_path / "c"
    for off in ("off", "0", "OFF"):
        monkeypatch.setenv(ENV, off)
        assert compilation_cache_dir() is None


@pytest.mark.skipif(sys.platform in ("darwin", "win32"), reason="XDG layout")
def test_default_is_the_user_cache_dir(monkeypatch, tmp_path):
    monkeypatch.delenv(ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert compilation_cache_dir() == tmp_path / "robtraj" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert compilation_cache_dir() == Path.home() / ".cache" / "robtraj" / "jax"


def test_suite_never_uses_the_home_cache():
    where = compilation_cache_dir()
    assert where is None or Path.home() / ".cache" not in where.parents
