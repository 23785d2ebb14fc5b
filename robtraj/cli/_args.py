"""argparse types for numbers the commands take; a bad value is one line and exit 2."""

from __future__ import annotations

import argparse


def seed(text: str) -> int:
    """A random seed: an integer >= 0 (numpy's generators refuse negative seeds)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"a seed must be >= 0, got {value}")
    return value
