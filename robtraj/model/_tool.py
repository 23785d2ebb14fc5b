"""The 18-LED hemispherical measuring tool of the paper's Figure 2."""

from __future__ import annotations

import numpy as np

from ..recording import Pose, Tool

TOOL_RADIUS = 0.05  # [m] hemisphere radius
TCP_OFFSET = 0.10  # [m] hemisphere centre (tool origin, TCP) along flange z


def hemispherical_tool() -> Tool:
    """The nominal LED tool: 18 LEDs on a hemisphere of radius 50 mm, emission axes radial.

    Tool frame: origin at the hemisphere centre (the TCP), z along the hemisphere's
    axis, away from the flange. LED 1 sits on the apex, LEDs 2–7 on a ring 40° from the
    axis, LEDs 8–18 on a ring 75° from it. Reference LEDs: 1, 2 and 4. The flange holds
    the tool 100 mm out along its z axis, unrotated.
    """
    polar = [0.0] + [np.deg2rad(40.0)] * 6 + [np.deg2rad(75.0)] * 11
    azimuth = (
        [0.0] + list(np.arange(6) * 2 * np.pi / 6) + list(np.arange(11) * 2 * np.pi / 11 + 0.3)
    )
    polar, azimuth = np.asarray(polar), np.asarray(azimuth)
    normals = np.stack(
        [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=-1
    )
    return Tool(
        led_ids=np.arange(1, 19, dtype=np.int32),
        constellation=TOOL_RADIUS * normals,
        normals=normals,
        reference_leds=np.array([1, 2, 4], np.int32),
        flange_from_tool=Pose(np.array([0.0, 0.0, TCP_OFFSET]), np.array([1.0, 0.0, 0.0, 0.0])),
    )
