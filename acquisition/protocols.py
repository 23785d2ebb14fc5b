"""Stream protocols the recorder understands: name -> decoder factory.

A decoder follows the interface of `acquisition.events`: ``feed(bytes) -> list[event]``
and a ``counters`` dict; it may also have ``finish()`` (the connection ended: flush an
incomplete message) and a ``blocks`` attribute, which the recorder sets to True to get
consecutive frames as `LedFrames` arrays instead of one `LedFrame` each. ``"robtraj"`` is our own protocol (PROTOCOL.md); ``"natnet"`` is
OptiTrack NatNet, imported lazily from `acquisition.natnet`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from robtraj import UserError

# name -> "module:attribute" of a zero-argument decoder factory
_REGISTRY: dict[str, str] = {
    "robtraj": "acquisition.protocol:Decoder",
    "natnet": "acquisition.natnet:NatNetStreamDecoder",
}


def names() -> list[str]:
    return sorted(_REGISTRY)


def register(name: str, target: str) -> None:
    """Add a protocol: `target` is ``"module:attribute"`` of a decoder factory."""
    _REGISTRY[name] = target


def decoder_factory(name: str) -> Callable[[], Any]:
    """The decoder factory for protocol `name`; `UserError` for an unknown or broken one."""
    try:
        target = _REGISTRY[name]
    except KeyError:
        raise UserError(f"unknown protocol {name!r}; known: {', '.join(names())}") from None
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
        return getattr(module, attr)
    except (ImportError, AttributeError) as e:
        raise UserError(f"protocol {name!r} is not available ({target}: {e})") from None


def make_decoder(name: str) -> Any:
    return decoder_factory(name)()
