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
    then onto the target. A robot advances to the next waypoint within ``switch_radius``.

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
                 clearance: float = 0.07, lane_spacing: float = 0.125, switch_radius: float = 0.03):
        self.scenario = scenario
        self.kp, self.kd, self.cruise = kp, kd, cruise_speed
        self.clearance, self.lane_spacing, self.switch_radius = clearance, lane_spacing, switch_radius
        self.reset()

    def reset(self) -> None:
        self._waypoints: list[np.ndarray] | None = None
        self._index: np.ndarray | None = None

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

    def __call__(self, state: FleetState) -> np.ndarray:
        pos, vel = state.positions, state.velocities
        if self._waypoints is None or len(self._waypoints) != len(pos):
            self._plan(pos, state.targets)
        acc = np.zeros_like(pos)
        limit = self.scenario.dynamics.accel_limit
        for i in range(len(pos)):
            path = self._waypoints[i]
            while self._index[i] < len(path) - 1 and np.linalg.norm(path[self._index[i]] - pos[i]) < self.switch_radius:
                self._index[i] += 1
            err = path[self._index[i]] - pos[i]
            dist = np.linalg.norm(err)
            if dist > 0 and self.kp * dist > self.kd * self.cruise:   # cap the approach speed
                err = err / dist * (self.kd * self.cruise / self.kp)
            a = self.kp * err - self.kd * vel[i]
            norm = np.linalg.norm(a)
            acc[i] = a if norm <= limit else a * (limit / norm)
        return acc
