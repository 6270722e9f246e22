"""A scripted formation-change controller: lanes around the object, then PD onto the targets.

No learning: it exists to prove the rest of the stack (safety layer, fleet transport) before a
trained policy is at hand, and as a reference point in reports.

Plan (made once, at the first call of an episode):
  * robots and targets are matched by row: the k-th robot from the top goes to the k-th target
    from the top (the same order as in the start formation, so paths do not cross);
  * robots in the upper half pass over the object, the lower half under it (the middle robot
    of an odd count goes over); robot j from the object on its side uses lane ``j``, at
    ``clearance + j * gap`` beyond the object's edge, where ``gap`` is ``lane_spacing`` or less
    if the lanes must squeeze between the object and the wall;
  * waypoints: out to the lane beside the start, along the lane to above/below the target,
    then onto the target. A robot advances to the next waypoint within ``switch_radius``, or,
    held within twice that, once it is nearer the waypoint after: a neighbour parked by the
    corner can keep it from the waypoint itself. A robot in motion never cuts a corner: beside
    the object, that would take it into the object's corner. Held means slower than
    ``held_speed``, or closer to its waypoint by less than ``held_speed * held_ticks * dt`` than
    ``held_ticks`` ticks ago: with 2 cm/s of velocity noise a robot held still reads faster than
    2 cm/s in most ticks, and only its lack of progress tells.

Swap rule (the formation is judged up to an assignment): the robots of one side leave their
lanes for the targets' column in lane order, each passing the targets nearer its lane. A robot
delayed on its way (a neighbour that went silent in its lane) would find one that came down
before it parked on a target in its path, and neither could move. So robot i, once past its
lane's start, swaps targets with a robot j on its final leg when j and j's target both lie on
i's leg down the column (within ``2 r + swap_margin`` of the segment from i's column waypoint
-- or i itself, on its final leg -- to i's target, strictly inside): j takes the farther target
and moves on, i the nearer one behind it. After a swap neither lies on the other's leg, and
without a late robot nobody does, so the planned assignment stands; robots not present (off
the link) are never swapped.

Control law per robot (m/s^2): ``a = kp * (w - p) - kd * v``, clipped to the acceleration limit,
with the speed along the path capped by shrinking the position term.
"""

from __future__ import annotations

import numpy as np

from sim.fleet import FleetState
from sim.scenario import Scenario


class ScriptedController:
    """``controller(state) -> (N, 2)`` accelerations for one episode; ``reset()`` between episodes."""

    def __init__(self, scenario: Scenario, kp: float = 6.0, kd: float = 4.0, cruise_speed: float = 0.3,
                 clearance: float = 0.07, lane_spacing: float = 0.125, switch_radius: float = 0.03,
                 swap_margin: float = 0.02, held_speed: float = 0.02, held_ticks: int = 10):
        self.scenario = scenario
        self.kp, self.kd, self.cruise = kp, kd, cruise_speed
        self.clearance, self.lane_spacing, self.switch_radius = clearance, lane_spacing, switch_radius
        self.swap_margin, self.held_speed, self.held_ticks = swap_margin, held_speed, held_ticks
        self.swaps = 0  # targets swapped by the swap rule over the controller's life
        self.reset()

    def reset(self) -> None:
        self._waypoints: list[np.ndarray] | None = None
        self._index: np.ndarray | None = None
        self._gaps: list[list[float]] = []   # per robot, its distances to its waypoint, oldest first

    def _plan(self, pos: np.ndarray, targets: np.ndarray) -> None:
        n = len(pos)
        poly = self.scenario.polygon
        top, bottom = poly[:, 1].max(), poly[:, 1].min()
        height = self.scenario.arena[1]
        r = self.scenario.robot_radius
        robots_by_y = np.argsort(-pos[:, 1])
        targets_by_y = np.argsort(-targets[:, 1])
        up = n // 2 + n % 2
        down = n - up
        # lanes share the room between the object and the wall, never closer than two radii + 1 cm
        room_up = height - r - 0.01 - (top + self.clearance)
        room_down = bottom - self.clearance - (r + 0.01)
        gap_up = min(self.lane_spacing, room_up / max(up - 1, 1))
        gap_down = min(self.lane_spacing, room_down / max(down - 1, 1))
        plans: list[np.ndarray] = [np.zeros((0, 2))] * n
        for rank, (i, k) in enumerate(zip(robots_by_y, targets_by_y, strict=True)):
            over = rank < up
            if over:
                y = top + self.clearance + (up - 1 - rank) * gap_up
            else:
                y = bottom - self.clearance - (rank - up) * gap_down
            plans[i] = np.array([[pos[i, 0], y], [targets[k, 0], y], targets[k]])
        self._waypoints = plans
        self._index = np.zeros(n, dtype=int)
        self._gaps = [[] for _ in range(n)]

    def _reached(self, path: np.ndarray, k: int, p: np.ndarray, v: np.ndarray, gaps: list[float]) -> bool:
        """Whether a robot at ``p`` moving at ``v`` is done with waypoint k of ``path``, its
        distances to it over the last ticks ``gaps`` (module docstring)."""
        gap = np.linalg.norm(path[k] - p)
        if gap < self.switch_radius:
            return True
        stuck = (len(gaps) >= self.held_ticks
                 and gaps[-self.held_ticks] - gap < self.held_speed * self.held_ticks * self.scenario.dynamics.dt)
        held = stuck or np.linalg.norm(v) < self.held_speed
        rounded = np.linalg.norm(path[k + 1] - p) < np.linalg.norm(path[k + 1] - path[k])
        return bool(held and rounded and gap < 2 * self.switch_radius)

    def _on_leg(self, start: np.ndarray, end: np.ndarray, point: np.ndarray) -> bool:
        """Whether ``point`` lies strictly inside segment start->end, within 2 r + margin of it."""
        seg = end - start
        length2 = float(seg @ seg)
        if length2 <= 0.0:
            return False
        s = float((point - start) @ seg) / length2
        lateral = float(np.linalg.norm(start + s * seg - point))
        return 0.0 < s < 1.0 and lateral < 2 * self.scenario.robot_radius + self.swap_margin

    def _swap_targets(self, pos: np.ndarray, present: np.ndarray) -> None:
        """The swap rule of the module docstring."""
        paths, last = self._waypoints, [len(p) - 1 for p in self._waypoints]
        for i in np.flatnonzero(present & (self._index >= 1)):
            leg_start = pos[i] if self._index[i] == last[i] else paths[i][last[i] - 1]
            for j in np.flatnonzero(present & (self._index == last)):
                t_i, t_j = paths[i][-1], paths[j][-1]
                if j != i and self._on_leg(leg_start, t_i, pos[j]) and self._on_leg(leg_start, t_i, t_j):
                    paths[i][-1], paths[j][-1] = t_j.copy(), t_i.copy()
                    self.swaps += 1
                    break

    def __call__(self, state: FleetState, present: np.ndarray | None = None) -> np.ndarray:
        """(N, 2) accelerations [m/s^2]; ``present`` (N,) bool: rows of robots on the link, the
        others stand in for absent ones (default: all present)."""
        pos, vel = state.positions, state.velocities
        if self._waypoints is None or len(self._waypoints) != len(pos):
            self._plan(pos, state.targets)
        self._swap_targets(pos, np.ones(len(pos), bool) if present is None else np.asarray(present, bool))
        acc = np.zeros_like(pos)
        limit = self.scenario.dynamics.accel_limit
        for i in range(len(pos)):
            path, gaps = self._waypoints[i], self._gaps[i]
            while self._index[i] < len(path) - 1 and self._reached(path, self._index[i], pos[i], vel[i], gaps):
                self._index[i] += 1
                gaps.clear()
            gaps.append(float(np.linalg.norm(path[self._index[i]] - pos[i])))
            del gaps[:-self.held_ticks]
            err = path[self._index[i]] - pos[i]
            dist = np.linalg.norm(err)
            if dist > 0 and self.kp * dist > self.kd * self.cruise:   # cap the approach speed
                err = err / dist * (self.kd * self.cruise / self.kp)
            a = self.kp * err - self.kd * vel[i]
            norm = np.linalg.norm(a)
            acc[i] = a if norm <= limit else a * (limit / norm)
        return acc
