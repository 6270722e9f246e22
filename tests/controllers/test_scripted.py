import numpy as np
import pytest
import torch

from controllers.scripted import ScriptedController
from sim.fleet import BatchedFleet, FleetState
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


def _state(sc, positions):
    n = len(positions)
    return FleetState(0.0, 0, np.asarray(positions, float), np.zeros((n, 2)), sc.targets,
                      np.array([*sc.object_center, 0.0]), tuple(f"r{i}" for i in range(n)))


@pytest.mark.parametrize("swap", [True, False])
def test_a_late_robot_swaps_targets_with_the_one_parked_in_its_path(swap):
    """paper-5: r3 (lane 0.835, target y 0.625) came down the column first and parked; r2
    (lane 0.72, target y 0.5) arrives late at its column waypoint, r3 in its way. With the
    swap rule r3 takes 0.5 and moves on down, r2 takes 0.625; without it r3 holds still."""
    sc = make_scenario("paper-5")
    ctl = ScriptedController(sc, swap_margin=0.02 if swap else -1.0)
    pos = sc.starts.copy()
    ctl(_state(sc, pos))                                     # plan from the start slots
    for r3_at in ([0.657, 0.835], [0.33, 0.835], [0.33, 0.625]):   # r3: lane, column, target
        pos[3] = r3_at
        ctl(_state(sc, pos))
    for r2_at in ([0.668, 0.72], [0.33, 0.72]):                    # r2, late: lane, column
        pos[2] = r2_at
        acc = ctl(_state(sc, pos))
    if swap:
        assert ctl.swaps == 1
        assert acc[3, 1] < -0.5 and abs(acc[3, 0]) < 1e-9     # r3 heads down to y = 0.5
        assert acc[2, 1] < -0.5                                # r2 follows to y = 0.625
    else:
        assert ctl.swaps == 0 and np.allclose(acc[3], 0.0)     # r3 parked: r2 is stuck behind


def test_without_a_late_robot_nobody_swaps():
    for name in ("paper-3", "paper-5"):
        sc = make_scenario(name)
        fleet, ctl = BatchedFleet(sc), ScriptedController(sc)
        state = fleet.reset(seed=1)
        for _ in range(sc.dynamics.episode_steps):
            fleet.send_accelerations(ctl(state))
            state = fleet.step()
        assert ctl.swaps == 0, name


@pytest.mark.parametrize("held_ticks", [10, 10_000])
def test_a_robot_that_makes_no_progress_counts_as_held_whatever_its_noisy_speed_reads(held_ticks):
    """paper-3, r0 (top robot, over the object) reaches its column waypoint's neighbourhood and
    is held 4 cm short of it (inside twice the 3 cm switch radius, nearer its target), while its
    velocity reads 3 cm/s, alternating (noise). After 10 ticks without progress it moves on to
    its target; with the progress rule off (held_ticks 10000) it stays on the waypoint."""
    sc = make_scenario("paper-3")
    ctl = ScriptedController(sc, held_ticks=held_ticks)
    pos = sc.starts.copy()
    ctl(_state(sc, pos))
    top = int(np.argmax(pos[:, 1]))
    lane_start, column, target = ctl._waypoints[top]
    pos[top] = lane_start
    ctl(_state(sc, pos))                                   # the lane's start is reached
    pos[top] = column + np.array([0.0, -0.04])             # 4 cm short, on the way to the target
    for k in range(12):
        state = _state(sc, pos)
        state.velocities[top] = [0.03 * (-1) ** k, 0.0]    # reads faster than held_speed
        ctl(state)
    assert ctl._index[top] == (2 if held_ticks == 10 else 1)
