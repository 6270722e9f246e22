"""What a long-running node does once at start-up, before its control loop."""

from __future__ import annotations

import gc


def freeze_start_up_heap() -> int:
    """Collect once, then move every object alive (torch, the modules, the control stack) out of
    the garbage collector's reach and return how many: a full collection of a bridge process
    (~280k objects) takes ~120 ms, 2.4 ticks at 20 Hz, and Python starts one whenever enough
    objects have survived. Afterwards the collector scans only what the loop allocates itself.
    ``formation bridge`` and ``formation fleet-sim`` (whose process holds torch too: ~220k
    objects, ~0.13 s) call it once they are set up and before they open their links: a pause
    once states flow would make a lock-stepped bridge's first tick answer a partial burst."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


__all__ = ["freeze_start_up_heap"]
