"""What a stream decoder yields, whatever the wire protocol (robtraj's own, NatNet, …).

A decoder is an object with ``feed(chunk: bytes) -> list[LedFrame | StatusMessage |
EndOfStream]`` (any split of the byte stream gives the same events) and a ``counters``
dict of error counts by kind; the recorder is written against this interface only.

A decoder may also yield `LedFrames`: consecutive LED frames as arrays, which the recorder
takes as a whole (robtraj's own decoder does when built with ``blocks=True``); it stands
for the `LedFrame`s its `frames()` gives, in order, with nothing between them.
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


@dataclasses.dataclass(frozen=True, eq=False)
class LedFrames:
    """K consecutive tracker frames of n LED records each, as arrays.

    `frame_counter` `(K,)` int64 as sent; `device_time` `(K,)` float64 [s]; `led_ids`
    `(K, n)` int64; `positions` `(K, n, 3)` float64 [m], NaN for an LED reported missing;
    `status` `(K, n)` uint8. Row j is the `LedFrame` ``frames()`` yields j-th.
    """

    frame_counter: np.ndarray
    device_time: np.ndarray
    led_ids: np.ndarray
    positions: np.ndarray
    status: np.ndarray

    def __len__(self) -> int:
        return int(self.frame_counter.shape[0])

    def frames(self):
        """The frames one by one, as a per-frame decoder yields them."""
        for j, (counter, t) in enumerate(
            zip(self.frame_counter.tolist(), self.device_time.tolist(), strict=True)
        ):
            yield LedFrame(counter, t, self.led_ids[j], self.positions[j], self.status[j])


@dataclasses.dataclass(frozen=True)
class StatusMessage:
    """Device status: `device_time` [s] and camera `temperature` [°C]."""

    device_time: float
    temperature: float


@dataclasses.dataclass(frozen=True)
class EndOfStream:
    """The device says the stream ends here."""
