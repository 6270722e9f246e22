"""Tells the operator when the safety layer holds a robot in place, and what holds it.

A robot is *held* once, for ``hold_s``, it has stayed within ``radius`` [m] of where the hold
began, farther than the scenario's tolerance from every target, with the stack's filter changing
its command (by more than ``FILTER_TOLERANCE`` [m/s^2]: :func:`stack.tick_types.filter_changed`, as the
episode figure counts it)
on at least half of those ticks; a stale row is not held (it is not listening, and is braked for
that). A robot standing next to one that stopped listening is the usual case: the bound round a
silent or stale robot keeps its neighbours off, for as long as it must.

The watch logs one warning when a hold reaches ``hold_s``: the robot, how long, its distance to
the nearest target, the robots not listening within ``NEAR_M`` of it (stale rows and silent robots,
and a tracker's obstacles by their edge, nearest first) and the filter's status (and reason) of that tick; and an info line when the
hold ends. A robot that creeps out of its 2 cm and is held again within ``RESUME_S`` and
``RESUME_M`` of the last hold continues that hold (one report, ``seconds`` from its start), so a
robot edging along a bound is one warning, not one a second.
`formation bridge` keeps the newest ``KEPT_REPORTS`` holds in its summary (``holds``)::

    {"robot": "r4", "from_tick": 20, "seconds": 11.0, "target_m": 0.37, "ended": false,
     "not_listening": [["r3", 0.126]], "filter": "intervened"}

(``from_tick`` counts the ticks the watch has seen.)
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from sim.fleet import FleetState
from stack.tick_types import TickResult, filter_changed

log = logging.getLogger(__name__)
NEAR_M = 0.3              # [m] robots not listening reported within this distance
KEPT_REPORTS = 1000       # the newest holds kept for the summary (a node may run for days)
RESUME_S, RESUME_M = 2.0, 0.05   # a hold again within this long and this near continues the last


@dataclass
class _Hold:
    anchor: np.ndarray
    from_tick: int
    ticks: int = 0
    pushed: int = 0
    report: dict | None = field(default=None)


class HoldWatch:
    """Per robot id, the hold in progress (module docstring); :meth:`observe` once a tick."""

    def __init__(self, dt: float, tolerance: float, accel_limit: float, hold_s: float = 1.0,
                 radius: float = 0.02):
        if not (dt > 0 and hold_s > 0 and radius > 0):
            raise ValueError(f"HoldWatch needs dt, hold_s and radius > 0, got {dt}, {hold_s}, {radius}")
        self.dt, self.tolerance, self.accel_limit = dt, tolerance, accel_limit
        self.hold_ticks, self.radius = int(np.ceil(hold_s / dt - 1e-9)), radius
        self._holds: dict[str, _Hold] = {}
        self._ended: dict[str, tuple[dict, int, np.ndarray]] = {}   # id -> last hold's report, end tick, anchor
        self.reports: list[dict] = []
        self._tick = 0

    def observe(self, state: FleetState, result: TickResult) -> None:
        """One tick: ``state`` as the stack was given it and the stack's answer."""
        pos, ids = np.asarray(state.positions, dtype=np.float64), state.robot_ids
        changed = filter_changed(result.a_nom, result.a_safe, self.accel_limit)
        stale = np.asarray(result.stale, dtype=bool)
        targets = np.asarray(state.targets, dtype=np.float64)
        to_target = np.linalg.norm(pos[:, None] - targets[None], axis=2).min(axis=1)
        for i, rid in enumerate(ids):
            eligible = not stale[i] and np.isfinite(pos[i]).all() and to_target[i] > self.tolerance
            hold = self._holds.get(rid)
            if hold is not None and (not eligible or np.linalg.norm(pos[i] - hold.anchor) > self.radius):
                self._end(rid)
                hold = None
            if not eligible:
                continue
            if hold is None:
                hold = self._holds[rid] = _Hold(anchor=pos[i].copy(), from_tick=self._tick)
            hold.ticks += 1
            hold.pushed += bool(changed[i])
            if hold.report is None and hold.ticks >= self.hold_ticks and 2 * hold.pushed >= hold.ticks:
                hold.report = self._resumed(rid, hold) or self._report(state, result, rid, i, to_target[i], stale)
            if hold.report is not None:
                hold.report["seconds"] = round((self._tick - hold.report["from_tick"] + 1) * self.dt, 2)
        for rid in set(self._holds) - set(ids):
            self._end(rid)
        self._tick += 1

    def _report(self, state: FleetState, result: TickResult, rid: str, i: int, to_target: float,
                stale: np.ndarray) -> dict:
        """A new hold's report, logged as a warning."""
        filt = str(result.safety_status or "") + (f" ({result.safety_reason})" if result.safety_reason else "")
        hold = self._holds[rid]
        report = {"robot": str(rid), "from_tick": hold.from_tick, "seconds": None,
                  "target_m": round(float(to_target), 3), "ended": False,
                  "not_listening": self._not_listening(state, stale, state.positions[i], i), "filter": filt}
        self.reports.append(report)
        if len(self.reports) > KEPT_REPORTS:
            del self.reports[0]
        log.warning("%s held in place by the safety filter for %.1f s, %.3f m from the nearest target; "
                    "robots not listening nearby: %s; filter: %s", rid, hold.ticks * self.dt, to_target,
                    report["not_listening"] or "none", filt or "-")
        return report

    def _resumed(self, rid: str, hold: _Hold) -> dict | None:
        """The report of this robot's last hold, if it ended lately and near here (RESUME_S, RESUME_M)."""
        last = self._ended.pop(rid, None)
        if last is None:
            return None
        report, ended_tick, anchor = last
        if (self._tick - ended_tick) * self.dt > RESUME_S or np.linalg.norm(hold.anchor - anchor) > RESUME_M:
            return None
        report["ended"] = False
        log.info("%s held again", rid)
        return report

    def _end(self, rid: str) -> None:
        hold = self._holds.pop(rid, None)
        if hold is not None and hold.report is not None:
            hold.report["ended"] = True
            self._ended[rid] = (hold.report, self._tick, hold.anchor)
            log.info("%s no longer held (%.1f s)", rid, hold.report["seconds"])

    @staticmethod
    def _not_listening(state: FleetState, stale: np.ndarray, at: np.ndarray, me: int) -> list:
        """[[id, distance m], ...] of stale rows, silent robots and obstacles (to their edge) within
        NEAR_M of ``at``."""
        near = [(rid, float(np.linalg.norm(state.positions[k] - at)))
                for k, rid in enumerate(state.robot_ids) if stale[k] and k != me]
        if state.silent is not None:
            near += [(rid, float(np.linalg.norm(p - at))) for rid, p in zip(state.silent.ids,
                                                                             state.silent.positions, strict=True)]
        if state.obstacles is not None:          # a tracker's obstacles, by their edge (robots listed above)
            obs = state.obstacles
            robots = obs.robots or (None,) * len(obs)
            near += [(f"obstacle {oid}", float(np.linalg.norm(p - at) - r)) for oid, p, r, robot in zip(
                obs.ids, obs.positions, obs.radii, robots, strict=True) if robot is None]
        return [[str(rid), round(d, 3)] for rid, d in sorted(near, key=lambda x: x[1]) if d <= NEAR_M]

    def summary(self) -> list[dict]:
        """Every hold reported so far (module docstring)."""
        return [dict(r) for r in self.reports]


class WatchedStack:
    """A stack (or a :class:`stack.recorder.RecordedStack`) whose ticks a :class:`HoldWatch`
    observes; anything else is the stack's own. With ``deferred`` the watch sees a tick only at
    :meth:`observe_last` (the bridge calls it once the tick's commands are out, so the watch
    does not delay them)."""

    def __init__(self, stack, watch: HoldWatch, deferred: bool = False):
        self.stack, self.watch, self.deferred = stack, watch, deferred
        self._last: tuple[FleetState, TickResult] | None = None

    def tick(self, state: FleetState) -> TickResult:
        result = self.stack.tick(state)
        self._last = (state, result)
        if not self.deferred:
            self.observe_last()
        return result

    def observe_last(self) -> None:
        """Let the watch see the last tick, once."""
        last, self._last = self._last, None
        if last is not None:
            self.watch.observe(*last)

    __call__ = tick

    def __getattr__(self, name: str):
        return getattr(self.stack, name)
