"""The fleet as the policy and docking see it: the commanded rows, then the silent robots.

A robot gone from the link (:class:`sim.fleet.SilentRobots`: its liveliness token lapsed, it
crashed or froze) still stands somewhere. The safety filter keeps it as an obstacle either way;
docking sees it too when its target is known, and so does the policy when it runs the larger
team (a network or exported file that takes N + M robots; a plain callable keeps its N rows):
as a teammate, appended after the N commanded rows, standing where the commands it was
sent must have left it (the centre of its branches' disc,
:meth:`controllers.safety.latency.LatencyPredictor.dead_reckoned`; its last report until the
filter has computed them), so the same frozen robot is seen the same whether the link still
lists it as a stale row or has dropped it. Its target stays its own: the team's assignment
and docking's "free target" count it. Its actions are computed and thrown away.
"""

from __future__ import annotations

import numpy as np

from controllers.safety.latency import LatencyPredictor
from sim.fleet import FleetState


def team_view(state: FleetState, predictor: LatencyPredictor | None) -> FleetState:
    """``state`` with its M silent robots appended as rows N..N+M-1 (positions and velocities
    (N+M, 2) [m, m/s], targets, ids, state ages, pending commands, no silent robots left),
    or ``state`` itself when there are none or their targets are unknown."""
    silent = state.silent
    if silent is None or not len(silent) or silent.targets is None:
        return state
    m = len(silent)
    pos, vel = silent.positions, silent.velocities
    if predictor is not None:
        pos, vel = predictor.dead_reckoned(silent.ids, pos, vel, silent.age_s, np.ones(m, dtype=bool),
                                           state.time)
    pending = None if state.commands_pending is None else np.concatenate(
        [state.commands_pending, silent.pending()])
    return state.replaced(positions=np.vstack([state.positions, pos]),
                          velocities=np.vstack([state.velocities, vel]),
                          targets=np.vstack([state.targets, silent.targets]),
                          robot_ids=tuple(state.robot_ids) + tuple(silent.ids),
                          state_age_s=np.concatenate([state.ages(), silent.age_s]),
                          commands_pending=pending, silent=None)


__all__ = ["team_view"]
