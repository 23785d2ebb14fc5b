"""Device side of robtraj: stream protocols, device emulator, fault-tolerant recorder.

`acquisition` may import `robtraj.recording`; `robtraj` imports `acquisition` only in its CLI.
"""

from .events import (
    EndOfStream as EndOfStream,
    LedFrame as LedFrame,
    LedFrames as LedFrames,
    StatusMessage as StatusMessage,
)
