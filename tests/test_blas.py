"""`robtraj._blas.serial_blas`: one BLAS thread inside, the user's setting after."""

import os

import numpy as np  # noqa: F401  (loads the BLAS library threadpoolctl controls)
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from robtraj._blas import serial_blas


def _threads() -> list[int]:
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="BLAS runs one thread anyway")
def test_one_blas_thread_inside_nested_calls_and_the_setting_restored_after():
    @serial_blas
    def inner():
        return _threads()

    @serial_blas
    def outer():
        return _threads(), inner(), _threads()

    with threadpool_limits(2, user_api="blas"):
        before = _threads()
        assert before and all(n == 2 for n in before)
        got = outer()
        assert all(n == 1 for part in got for n in part)
        assert _threads() == before
