"""run_episode: how an episode is judged in each world."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.docking import DockingConfig
from sim.fleet import BatchedFleet
from sim.scenario import transport_scenario
from stack.episodes import run_episode
from stack.pipeline import ControlStack, StackConfig


@pytest.mark.parametrize(("push", "kind"), [((1.0, 0.0), "wall_collisions"), ((-1.0, 0.0), "object_collisions")])
def test_an_episode_in_the_batched_world_counts_the_touches_the_world_stops(push, kind):
    """paper-3 driven at full thrust for 60 ticks, bare: each robot ends stopped touching the wall
    (x = 1 - 0.04 = 0.96) or the object (0.6 + 0.04 = 0.64), one onset each. The world puts a
    stopped robot exactly at contact, which positions alone (< r - 1e-6) did not show: 0 before."""
    paper3 = transport_scenario(3, name="paper-3")
    bare = StackConfig(safety=False, mec=False, docking=DockingConfig(enabled=False))
    fleet = BatchedFleet(paper3)
    metrics = run_episode(fleet, ControlStack(paper3, lambda s: np.tile(push, (3, 1)), bare), seed=0, steps=60)
    assert fleet.env.pos[0, :, 0].numpy() == pytest.approx([0.96 if push[0] > 0 else 0.64] * 3, abs=1e-9)
    assert getattr(metrics, kind) == 3 and metrics.collided and not metrics.success
