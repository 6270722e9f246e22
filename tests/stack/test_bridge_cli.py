"""`formation bridge`'s controllers, in process: the scripted fleet controller across episodes."""

from __future__ import annotations

from sim.pymunk_world import PymunkWorld
from sim.scenario import make_scenario
from stack.commands.bridge import build_stack
from stack.pipeline import run_episode


def test_the_scripted_fleet_controller_plans_afresh_each_episode():
    """One stack over three pymunk episodes, reset between them as the bridge resets it at a fleet
    episode boundary: every episode ends home. Before the wrapper passed the reset on, episodes 2
    and 3 ran on the first one's finished plan, heading straight for the targets through the object,
    and ended 0.196 m off with the filter intervening every tick."""
    sc = make_scenario("paper-5")
    world, stack = PymunkWorld(sc), build_stack(sc, "scripted", safety=True, mec=True)
    results = [run_episode(world, stack, seed) for seed in range(3)]
    assert [m.success for m in results] == [True, True, True]
    assert max(m.final_distance for m in results) < 0.005
