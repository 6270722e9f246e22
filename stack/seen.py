"""What a tracker over the arena reports (:attr:`sim.fleet.FleetState.obstacles`), as the
safety filter takes it: discs of things the controller does not command, appended as fixed
obstacles, and sightings of the fleet's own robots, which bound a silent robot once it is at
rest (:mod:`controllers.safety.silent_reach`, Seen at rest) and never hold a robot itself.

Both reach as far as the tracker says each may move by the end of the tick the new command acts
in: an obstacle of radius ``R`` seen ``age`` ago moving at most ``s`` is a fixed row of robot
radius ``r`` grown by ``max(R - r, 0) + s (age + L + dt)``, with ``L`` the latency bound.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from controllers.safety.barrier import SafetyConfig
from controllers.safety.prediction import Prediction
from controllers.safety.relevance import without_idle_fixed_rows
from controllers.safety.silent_reach import Sighting
from sim.fleet import Obstacles
from sim.scenario import Dynamics


def robot_sightings(obstacles: Obstacles, ids: Sequence[str], now: float, reach_s: float,
                    robot_radius: float) -> tuple[dict[int, Sighting], Obstacles | None]:
    """``(sightings of the robots in ids, by row; the other obstacles, None if none)``.

    Args:
        obstacles: the tracker's K discs; ids: the filter's robot rows (silent robots too).
        now: the state's time [s]; reach_s: the latency bound plus one tick [s].
        robot_radius: r [m].
    """
    seen, rest = obstacles.split(ids)
    row = {name: i for i, name in enumerate(ids)}
    sightings = {}
    for name, k in seen.items():
        speed = float(obstacles.speed[k])
        grow = max(float(obstacles.radii[k]) - robot_radius, 0.0) + speed * (float(obstacles.age_s[k]) + reach_s)
        sightings[row[name]] = Sighting(obstacles.positions[k].copy(), grow, speed, now - float(obstacles.age_s[k]))
    return sightings, rest


def with_obstacles(prediction: Prediction | None, obstacles: Obstacles, pos: np.ndarray, vel: np.ndarray,
                   fixed: np.ndarray, reach_s: float, robot_radius: float) -> Prediction:
    """``prediction`` (with the latency prediction off: the (M, 2) rows as measured, ``fixed``
    (M,) bool) with the K obstacles appended, each reaching ``age + reach_s`` [s] at its speed."""
    prediction = prediction or Prediction.as_measured(pos, vel, fixed)
    return prediction.with_obstacles(obstacles.positions, obstacles.radii, obstacles.age_s + reach_s, obstacles.speed,
                                     robot_radius)


def binding_discs(seen: Prediction, first: int, centres: np.ndarray, config: SafetyConfig, dynamics: Dynamics,
                  robot_radius: float, every_disc: bool = False) -> tuple[Prediction, np.ndarray]:
    """``(the filter's prediction, (K', 2) centres of the discs in it)``: ``seen``, whose rows
    ``first..`` are the K discs at ``centres`` (K, 2), without the discs that cannot bind a
    listening robot this tick (:func:`controllers.safety.relevance.without_idle_fixed_rows`: the
    filter's answer is the same); with ``every_disc``, all of them."""
    if every_disc:
        return seen, centres
    kept_rows, kept = without_idle_fixed_rows(seen, first, config, dynamics, robot_radius)
    return kept_rows, centres[kept[first:]]


__all__ = ["binding_discs", "robot_sightings", "with_obstacles"]
