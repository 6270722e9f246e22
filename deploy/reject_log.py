"""Rejections reported while a node runs, not only in its exit report.

A node (the bridge, the simulated fleet) calls :meth:`RejectLog.poll` once a tick; when messages
were rejected since the last report and ``interval_s`` has passed, one WARNING line says how many
and why (``docs/wire-format.md`` reasons), e.g.::

    bridge: 3 messages rejected in the last 1.0 s: {'FROM_FUTURE': 1, 'STALE': 2}

The running totals stay in the exit report (``rejects``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

log = logging.getLogger(__name__)


class RejectLog:
    """Logs the change of ``snapshot()`` (counts by reason) at most once per ``interval_s`` [s]."""

    def __init__(self, node: str, snapshot: Callable[[], dict[str, int]], interval_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic):
        if not interval_s > 0:
            raise ValueError(f"interval_s must be > 0 seconds, got {interval_s!r}")
        self.node, self.snapshot, self.interval_s, self.clock = node, snapshot, interval_s, clock
        self._reported: dict[str, int] = {}
        self._last = clock()

    def poll(self) -> dict[str, int] | None:
        """Log and return the rejections since the last report (None: nothing new, or too soon)."""
        now = self.clock()
        if now - self._last < self.interval_s:
            return None
        counts = self.snapshot()
        new = {k: n - self._reported.get(k, 0) for k, n in sorted(counts.items())
               if n > self._reported.get(k, 0)}
        if not new:
            return None
        log.warning("%s: %d messages rejected in the last %.1f s: %s", self.node, sum(new.values()),
                    now - self._last, new)
        self._reported, self._last = counts, now
        return new
