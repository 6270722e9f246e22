"""Checks of the controllers' settings: one wording for a bad number, the field named."""

from __future__ import annotations

import math
from collections.abc import Iterable


def check_numbers(config: object, names: Iterable[str], prefix: str, error: type[Exception],
                  *, positive: bool = False) -> None:
    """Raise ``error`` naming ``prefix.name`` for the first of ``names`` on ``config`` that is
    not a finite number >= 0 (> 0 with ``positive``); booleans are not numbers here."""
    for name in names:
        value = getattr(config, name)
        number = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        if not number or value < 0 or (positive and value == 0):
            rule = "a positive finite number" if positive else "a finite number >= 0"
            raise error(f"{prefix}.{name} must be {rule}, got {value!r}")


__all__ = ["check_numbers"]
