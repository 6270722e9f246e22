"""argparse types shared by the commands: a bad value exits 2 with the flag named, no traceback."""

from __future__ import annotations

import argparse


def seed(text: str) -> int:
    """A seed: an integer in 0 .. 2**32 - 1 (numpy's seed range)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer seed >= 0, got {text!r}") from None
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"a seed must be in 0 .. 2**32 - 1, got {value}")
    return value


def positive(text: str) -> int:
    """A positive integer (a count)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


__all__ = ["positive", "seed"]
