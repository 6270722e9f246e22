import numpy as np
import torch

from controllers.scripted import ScriptedController
from sim.fleet import BatchedFleet
from sim.metrics import collision_events, episode_outcome
from sim.scenario import make_scenario


def run_episode(name: str, seed: int):
    sc = make_scenario(name)
    fleet, ctl = BatchedFleet(sc), ScriptedController(sc)
    state = fleet.reset(seed=seed)
    collided = False
    for _ in range(sc.dynamics.episode_steps):
        fleet.send_accelerations(ctl(state))
        state = fleet.step()
        ev = collision_events(torch.tensor(state.positions)[None], torch.tensor(sc.polygon),
                              sc.robot_radius, sc.arena)
        collided |= bool(ev.any.any())
    return episode_outcome(torch.tensor(state.positions)[None], torch.tensor(state.targets)[None],
                           torch.tensor([collided]), sc.target_tolerance)


def test_scripted_controller_solves_the_paper_presets():
    for name in ("paper-3", "paper-4", "paper-5"):
        outcomes = [run_episode(name, seed) for seed in range(3)]
        assert all(o.success.item() for o in outcomes), name
        assert max(o.final_distance.item() for o in outcomes) < 0.01


def test_commands_respect_the_acceleration_limit():
    sc = make_scenario("paper-3")
    fleet, ctl = BatchedFleet(sc), ScriptedController(sc)
    state = fleet.reset(seed=0)
    for _ in range(20):
        a = ctl(state)
        assert np.all(np.linalg.norm(a, axis=1) <= sc.dynamics.accel_limit + 1e-12)
        fleet.send_accelerations(a)
        state = fleet.step()
