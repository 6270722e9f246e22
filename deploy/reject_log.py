"""Rejections reported while a node runs, not only in its exit report.

A node (the bridge, the simulated fleet) calls :meth:`RejectLog.poll` once a tick; when messages
were rejected since the last report and ``interval_s`` has passed, one WARNING line says how many
and why (``docs/wire-format.md`` reasons), e.g.::

    bridge: 3 messages rejected in the last 1.0 s: {'FROM_FUTURE': 1, 'STALE': 2}

The running totals stay in the exit report (``rejects``). :class:`Throttle` is the rate limit
alone, for other reports made at most once per interval (the bridge's re-arm alarm).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

log = logging.getLogger(__name__)


class Throttle:
    """At most one report per ``interval_s`` [s] of ``clock``: :meth:`due` is the time since the
    last report (or since the start) once that is at least ``interval_s``, else None;
    :meth:`done` marks a report made now."""

    def __init__(self, interval_s: float = 1.0, clock: Callable[[], float] = time.monotonic):
        if not interval_s > 0:
            raise ValueError(f"interval_s must be > 0 seconds, got {interval_s!r}")
        self.interval_s, self.clock = interval_s, clock
        self._last = clock()

    def due(self) -> float | None:
        since = self.clock() - self._last
        return since if since >= self.interval_s else None

    def done(self) -> None:
        self._last = self.clock()


class RejectLog:
    """Logs the change of ``snapshot()`` (counts by reason) at most once per ``interval_s`` [s]
    (:class:`Throttle`), as ``<node>: <n> <what> in the last <s> s: {reason: n}``."""

    def __init__(self, node: str, snapshot: Callable[[], dict[str, int]], interval_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic, what: str = "messages rejected"):
        self.node, self.snapshot, self.what = node, snapshot, what
        self._throttle = Throttle(interval_s, clock)
        self._reported: dict[str, int] = {}

    def poll(self) -> dict[str, int] | None:
        """Log and return the rejections since the last report (None: nothing new, or too soon)."""
        since = self._throttle.due()
        if since is None:
            return None
        counts = self.snapshot()
        new = {k: n - self._reported.get(k, 0) for k, n in sorted(counts.items())
               if n > self._reported.get(k, 0)}
        if not new:
            return None
        log.warning("%s: %d %s in the last %.1f s: %s", self.node, sum(new.values()), self.what,
                    since, new)
        self._reported = counts
        self._throttle.done()
        return new
