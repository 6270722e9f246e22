import numpy as np
import pytest
import torch

from sim.fleet import BatchedFleet, Fleet, FleetState
from sim.scenario import make_scenario


def test_batched_fleet_implements_the_interface_and_moves():
    fleet = BatchedFleet(make_scenario("paper-3"))
    assert isinstance(fleet, Fleet)
    s0 = fleet.reset(seed=0)
    fleet.send_accelerations(np.tile([0.0, -1.0], (3, 1)))
    s1 = fleet.step()
    assert s1.step == 1 and s1.time == pytest.approx(0.05)
    assert np.allclose(s1.positions - s0.positions, [[0.0, -0.0025]] * 3)
    assert np.allclose(s1.targets, make_scenario("paper-3").targets)


def test_batched_fleet_refuses_bad_commands():
    fleet = BatchedFleet(make_scenario("paper-3"))
    fleet.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(num_robots, 2\) = \(3, 2\)"):
        fleet.send_accelerations(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="NaN or inf"):
        fleet.send_accelerations(np.array([[np.nan, 0.0]] * 3))


def test_fleet_state_checks_shapes():
    with pytest.raises(ValueError, match=r"FleetState.velocities must have shape \(2, 2\)"):
        FleetState(time=0.0, step=0, positions=np.zeros((2, 2)), velocities=np.zeros((3, 2)),
                   targets=np.zeros((2, 2)), object_pose=np.zeros(3))


def test_fleet_state_checks_the_pending_counts():
    kw = dict(time=0.0, step=0, positions=np.zeros((2, 2)), velocities=np.zeros((2, 2)),
              targets=np.zeros((2, 2)), object_pose=np.zeros(3))
    for bad in (np.array([1, -2]), np.array([1.0, 2.0]), np.array([1, 2, 3])):
        with pytest.raises(ValueError, match="FleetState.commands_pending must be 2 integers >= 0"):
            FleetState(**kw, commands_pending=bad)
    state = FleetState(**kw, commands_pending=[2, -1])
    assert state.pending().tolist() == [2, -1]
    assert FleetState(**kw).pending().tolist() == [-1, -1]


def test_obstacles_split_names_a_robot_by_its_freshest_sighting_and_keeps_none_of_its_own():
    from sim.fleet import Obstacles

    seen = Obstacles(("#1", "#2", "#3", "#4"), [[0.2, 0.2], [0.21, 0.2], [0.5, 0.9], [0.8, 0.8]],
                     [0.04, 0.04, 0.04, 0.05], [0.02, 0.10, 0.0, 0.0], [0.0, 0.0, 0.0, 0.3],
                     robots=("a", "a", "b", None))
    rows, rest = seen.split(("a", "b"))
    assert rows == {"a": 0, "b": 2}
    assert rest.ids == ("#4",) and rest.robots == (None,)
    rows, rest = seen.split(("c",))
    assert rows == {} and rest is seen


def test_building_a_batched_fleet_leaves_torchs_global_random_stream_alone():
    torch.manual_seed(0)
    expected = torch.rand(3)
    torch.manual_seed(0)
    BatchedFleet(make_scenario("paper-3"))
    assert torch.equal(torch.rand(3), expected)
