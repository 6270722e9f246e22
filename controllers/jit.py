"""Compiled kernels of the control tick: one decorator, where the machine code is cached, warm-up.

At five robots every array of the tick holds a few dozen numbers, so a numpy expression costs
its call overhead (1-3 us) whatever it computes, and a stage of 40 such expressions costs
~100 us. The stages that ran that way (the compensator's observer bank, the latency prediction,
the position estimator) are written once as loops compiled by numba (:func:`kernel`): the same
IEEE operations in the same order, so they agree with the numpy formulation to the last bit
(the parity tests keep that formulation as the reference).

Compiled code is cached next to the module (``__pycache__``; numba falls back to a per-user
cache where that is not writable), so only the first process on a machine compiles (a few
seconds); later ones load it (~0.3 s on the first kernel, for numba itself). A long-running
node calls :func:`warm_up` before its first deadline. ``NUMBA_DISABLE_JIT=1`` runs the kernels as
plain Python (slow, the same answers) for debugging.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import numba
import numpy as np

F = TypeVar("F", bound=Callable)

_WARM_UPS: list[Callable[[], object]] = []
KERNELS: list[numba.core.registry.CPUDispatcher] = []
"""Every kernel defined so far. Each should end up with one compiled signature: its callers pass
fixed types (C-contiguous float64/int64/bool arrays, float scalars), so no tick compiles."""


def kernel(fn: F) -> F:
    """Compile ``fn`` with numba (no Python objects, no fast-math: IEEE results, cached on disk)."""
    compiled = numba.njit(cache=True, nogil=True, fastmath=False)(fn)
    KERNELS.append(compiled)
    return compiled


def register_warm_up(fn: Callable[[], object]) -> Callable[[], object]:
    """Register a function that calls its module's kernels once on representative types."""
    _WARM_UPS.append(fn)
    return fn


def require_shapes(where: str, **arrays: tuple[np.ndarray, tuple[int, ...]]) -> None:
    """Raise ValueError naming the first ``name=(array, shape)`` whose shape differs: a kernel
    reads its arrays unchecked, so its caller checks them."""
    for name, (array, shape) in arrays.items():
        got = array.shape if isinstance(array, np.ndarray) else np.shape(array)
        if got != shape:
            raise ValueError(f"{where}: {name} must have shape {shape}, got {got}")


def f64(x: np.ndarray) -> np.ndarray:
    """``x`` as a C-contiguous float64 array (what the kernels take; no copy if it is one)."""
    return np.ascontiguousarray(x, dtype=np.float64)


def warm_up() -> None:
    """Compile (or load from the cache) every registered kernel now, not at the first tick; each
    module's kernels once per process (a kernel keeps what it compiled)."""
    while _WARM_UPS:
        _WARM_UPS.pop(0)()


__all__ = ["KERNELS", "f64", "kernel", "register_warm_up", "require_shapes", "warm_up"]
