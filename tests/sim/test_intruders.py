"""Intruders of the simulated fleet: their path, what a user may write, and what the watch
counts (hand-worked cases)."""

from __future__ import annotations

import numpy as np
import pytest

from sim.intruders import Intruder, IntruderFleet, IntruderWatch


def test_an_intruder_walks_its_line_between_its_ticks():
    walker = Intruder(0.05, (0.5, 1.0), (0.0, -0.2), enter_tick=10, leave_tick=20)
    assert [walker.present(k) for k in (9, 10, 19, 20)] == [False, True, True, False]
    np.testing.assert_allclose(walker.centre(15, 0.05), [0.5, 1.0 - 0.2 * 5 * 0.05])
    assert walker.reported_speed == pytest.approx(0.2)
    assert Intruder(0.05, (0, 0), (0.3, 0.4), max_speed=0.7).reported_speed == 0.7


def test_what_a_user_writes_is_parsed_or_refused_by_name():
    assert Intruder.parse("radius=0.06,x=0.5,y=1.1,vy=-0.2,enter=20,leave=120") == \
        Intruder(0.06, (0.5, 1.1), (0.0, -0.2), 20, 120)
    for text, match in (("radius=0.06,x=0.5", "y missing"), ("radius=0.06,x=0.5,y=1,z=2", "FIELD one of"),
                        ("radius=abc,x=0.5,y=1", "radius='abc' is not a number"),
                        ("radius=0.06,x=0.5,y=1,enter=2.5", "enter=2.5 must be a whole tick"),
                        ("radius=0,x=0.5,y=1", "radius must be > 0"),
                        ("radius=0.06,x=0.5,y=1,enter=5,leave=5", "leave must be a tick after enter"),
                        ("radius=0.06,x=0.5,y=1,vx=0.3,max_speed=0.1", "max_speed must be >= its speed 0.300"),
                        ("radius=0.06,x=nan,y=1", "start must be a finite")):
        with pytest.raises(ValueError, match=match):
            Intruder.parse(text)


def test_the_watch_tells_driving_in_from_being_walked_into():
    """A 0.05 m intruder at (0.5, 0.5), robots of radius 0.04: one robot 0.08 m from its centre
    (10 mm deep) moving towards it at 0.1 m/s drove in; one as deep moving away did not; one
    0.1 m away is 10 mm clear."""
    watch = IntruderWatch([Intruder(0.05, (0.5, 0.5))], robot_radius=0.04, dt=0.05)
    assert watch.summary() == {"min_gap_mm": None, "drive_in_ticks": 0, "max_drive_in_speed": 0.0}
    watch.observe(0, np.array([[0.6, 0.5]]), np.array([[-0.1, 0.0]]))
    assert watch.summary() == {"min_gap_mm": 10.0, "drive_in_ticks": 0, "max_drive_in_speed": 0.0}
    watch.observe(1, np.array([[0.58, 0.5], [0.5, 0.42]]), np.array([[0.1, 0.0], [0.0, -0.1]]))
    assert watch.summary() == {"min_gap_mm": -10.0, "drive_in_ticks": 0, "max_drive_in_speed": 0.0}
    watch.observe(2, np.array([[0.58, 0.5]]), np.array([[-0.1, 0.0]]))
    assert watch.summary() == {"min_gap_mm": -10.0, "drive_in_ticks": 1, "max_drive_in_speed": 0.1}
    gone = IntruderWatch([Intruder(0.05, (0.5, 0.5), leave_tick=1)], 0.04, 0.05)
    gone.observe(1, np.array([[0.5, 0.5]]), np.array([[0.0, 0.0]]))
    assert gone.summary()["min_gap_mm"] is None


def test_a_fleet_with_intruders_shows_them_as_a_late_tracker_would():
    """A walker entering on tick 2 at (0.5, 0.9), 0.2 m/s down, sighted two ticks late: no
    obstacle before tick 4; on tick 5 the state shows it where it was on tick 3 (0.9 - 0.2 x
    0.05), 0.1 s old, at its reported top speed; a reset starts the walk and the watch over."""
    from sim.pymunk_world import PymunkWorld
    from sim.scenario import make_scenario

    sc = make_scenario("paper-3")
    fleet = IntruderFleet(PymunkWorld(sc), [Intruder(0.05, (0.5, 0.9), (0.0, -0.2), enter_tick=2, max_speed=0.3)],
                          sighting_delay_ticks=2)
    seen = [fleet.reset(seed=0).obstacles]
    for _ in range(5):
        fleet.send_accelerations(np.zeros((3, 2)))
        seen.append(fleet.step().obstacles)
    assert [s is None for s in seen] == [True, True, True, True, False, False]
    obs = seen[5]
    assert obs.ids == ("#0",)
    np.testing.assert_allclose(obs.positions, [[0.5, 0.9 - 0.2 * 0.05]])
    np.testing.assert_allclose(obs.age_s, [0.1])
    np.testing.assert_allclose(obs.speed, [0.3])
    assert fleet.watch.min_gap < np.inf and fleet.outcome() is not None     # the world's own calls pass through
    assert fleet.reset(seed=1).obstacles is None and fleet.watch.min_gap == np.inf
    with pytest.raises(ValueError, match="sighting_delay_ticks"):
        IntruderFleet(PymunkWorld(sc), [], sighting_delay_ticks=-1)
