"""robtraj: measure what an industrial robot really does.

Importing robtraj enables JAX float64 (``jax_enable_x64``): estimation runs in
double precision everywhere (DESIGN section 3). The kernels in
``robtraj.jax_ops`` are dtype-generic, so float32 inputs stay float32. It also asks
XLA's CPU compiler for its faster-compiling loop emitters (`robtraj._xla_flags`) unless
JAX's backend has started already.
"""

import importlib.metadata

from ._xla_flags import set_compile_flags

set_compile_flags()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from ._errors import UserError as UserError  # noqa: E402
from ._recording_reader import open_recording as open_recording  # noqa: E402
from .recording import (  # noqa: E402
    Pose as Pose,
    Probe as Probe,
    Program as Program,
    Recording as Recording,
    RecordingError as RecordingError,
    RobotLog as RobotLog,
    Tool as Tool,
    Truth as Truth,
    read_recording as read_recording,
    write_recording as write_recording,
)

try:
    __version__ = importlib.metadata.version("robtraj")
except importlib.metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0"
