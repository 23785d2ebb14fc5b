"""What a stream decoder yields, whatever the wire protocol (robtraj's own, NatNet, …).

A decoder is an object with ``feed(chunk: bytes) -> list[LedFrame | StatusMessage |
EndOfStream]`` (any split of the byte stream gives the same events) and a ``counters``
dict of error counts by kind; the recorder is written against this interface only.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class LedFrame:
    """One tracker frame.

    `frame_counter` is the device counter as sent (it may wrap); `device_time` [s];
    `led_ids` `(n,)` int; `positions` `(n, 3)` float64 [m] in the camera frame, NaN for
    an LED reported missing; `status` `(n,)` uint8 (0 ok, 1 missing, 2 out of volume,
    3 low signal).
    """

    frame_counter: int
    device_time: float
    led_ids: np.ndarray
    positions: np.ndarray
    status: np.ndarray


@dataclasses.dataclass(frozen=True)
class StatusMessage:
    """Device status: `device_time` [s] and camera `temperature` [°C]."""

    device_time: float
    temperature: float


@dataclasses.dataclass(frozen=True)
class EndOfStream:
    """The device says the stream ends here."""
