"""stack.hold_watch: the operator is told when the filter holds a robot in place, and by whom."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from sim.fleet import FleetState, SilentRobots
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import make_scenario
from stack.hold_watch import HoldWatch, WatchedStack
from stack.tick_types import PolicyStatus, TickResult
from tests.stack.test_team_view import DroppedFromLink

DT = 0.05


def _state(pos, targets, silent_at=None) -> FleetState:
    pos = np.asarray(pos, dtype=float)
    silent = None if silent_at is None else SilentRobots(("r9",), np.array([silent_at]), np.zeros((1, 2)), [0.5])
    return FleetState(time=0.0, step=0, positions=pos, velocities=np.zeros_like(pos),
                      targets=np.asarray(targets, dtype=float), object_pose=np.array([0.5, 0.5, 0.0]),
                      robot_ids=tuple(f"r{i}" for i in range(len(pos))), silent=silent)


def _result(a_nom, a_safe, stale=(False, False), reason="") -> TickResult:
    return TickResult(a_nom=np.asarray(a_nom, float), a_safe=np.asarray(a_safe, float), a_cmd=np.asarray(a_safe, float),
                      policy_status=PolicyStatus.OK, safety_status=None, mec_status=None, safety_reason=reason,
                      stale=np.asarray(stale, bool))


def test_a_robot_pushed_against_the_filter_for_a_second_is_reported_once_with_what_holds_it(caplog):
    """r0 creeps 1 mm a tick (19 mm in 20 ticks: still inside the 2 cm), 0.2 m from its target,
    its push of (1, 0) m/s^2 cut to (0.2, 0) on 12 of 20 ticks, beside a silent r9 9 cm away:
    reported at the 20th tick (1 s), not before, once, naming r9; r1 on its target is never
    held; r0 stepping 3 cm ends the hold."""
    watch = HoldWatch(DT, tolerance=0.05, accel_limit=1.0)
    targets = [[0.5, 0.2], [0.8, 0.8]]
    with caplog.at_level(logging.INFO, logger="stack.hold_watch"):
        for k in range(25):
            state = _state([[0.3 + 0.001 * min(k, 19), 0.2], [0.8, 0.8]], targets, silent_at=[0.39, 0.2])
            cut = k % 5 != 0 and k % 5 != 4           # 3 of every 5 ticks: 12 of the first 20
            watch.observe(state, _result([[1.0, 0.0], [0.0, 0.0]], [[0.2 if cut else 1.0, 0.0], [0.0, 0.0]],
                                         reason="post-check braked r0" if cut else ""))
            if k == 18:
                assert watch.summary() == []
        (report,) = watch.summary()
        assert report["robot"] == "r0" and report["from_tick"] == 0 and report["seconds"] == 1.25
        assert report["target_m"] == pytest.approx(0.181) and report["ended"] is False
        assert report["not_listening"] == [["r9", pytest.approx(0.071)]]
        assert report["filter"] == ""            # no filter status in these hand-built ticks
        watch.observe(_state([[0.35, 0.2], [0.8, 0.8]], targets), _result([[1.0, 0.0], [0, 0]], [[1.0, 0.0], [0, 0]]))
    assert watch.summary()[0]["ended"] is True
    lines = [(r.levelno, r.getMessage()) for r in caplog.records]
    assert len(lines) == 2 and lines[0][0] == logging.WARNING and lines[1][0] == logging.INFO
    assert "r0 held in place" in lines[0][1] and "r9" in lines[0][1]
    assert "r0 no longer held (1.2 s)" in lines[1][1]


def test_a_robot_edging_along_a_bound_is_one_hold(caplog):
    """r0 held for 1.5 s, steps 3 cm (the hold ends), and is held again at once for 1.5 s, 3 cm
    from where the first began: one report from tick 0, 3.05 s long, one warning. Held again
    only after 3 s away, it is a second report."""
    watch = HoldWatch(DT, tolerance=0.05, accel_limit=1.0)
    targets = [[0.8, 0.2], [0.8, 0.8]]

    def hold(x: float, ticks: int) -> None:
        for _ in range(ticks):
            watch.observe(_state([[x, 0.2], [0.8, 0.8]], targets), _result([[1.0, 0.0], [0, 0]], [[0.0, 0.0], [0, 0]]))

    with caplog.at_level(logging.WARNING, logger="stack.hold_watch"):
        hold(0.30, 30)
        hold(0.33, 31)
        (report,) = watch.summary()
        assert report["from_tick"] == 0 and report["seconds"] == 3.05 and report["ended"] is False
        for k in range(60):                       # 3 s moving freely, far from the anchors
            watch.observe(_state([[0.4 + 0.01 * k, 0.5], [0.8, 0.8]], targets),
                          _result([[1.0, 0.0], [0, 0]], [[1.0, 0.0], [0, 0]]))
        hold(0.33, 30)
    assert [r["from_tick"] for r in watch.summary()] == [0, 121]
    assert len(caplog.records) == 2


@pytest.mark.parametrize("case", ["policy's own", "stale", "on target"])
def test_a_robot_standing_by_its_own_choice_or_not_listening_is_not_held(case):
    """The same second standing still, but the filter never changes the command (the policy
    holds it), or the robot is a stale row (braked because it does not listen), or it stands
    within tolerance of a target: no report."""
    watch = HoldWatch(DT, tolerance=0.05, accel_limit=1.0)
    goal = [0.32, 0.2] if case == "on target" else [0.5, 0.2]
    for _ in range(40):
        safe = [[1.0, 0.0], [0, 0]] if case == "policy's own" else [[0.0, 0.0], [0, 0]]
        watch.observe(_state([[0.3, 0.2], [0.8, 0.8]], [goal, [0.8, 0.8]]),
                      _result([[1.0, 0.0], [0, 0]], safe, stale=(case == "stale", False)))
    assert watch.summary() == []


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="hold_s"):
        HoldWatch(DT, 0.05, 1.0, hold_s=0.0)


@pytest.mark.parametrize("detour", [False, True])
def test_the_robots_held_by_a_dropped_robot_are_reported_naming_it(detour):
    """Scripted paper-5, robot 3 frozen at tick 20 and dropped from the link (the case of
    tests/stack/test_team_view.py): without detours robots 4 and 2 stand at the filter's bound
    round r3 from ticks 20 and 21 to the end (11.0 and 10.95 s), 0.37 and 0.35 m from the
    nearest target, each reported once with r3 named the robot not listening beside it (0.126
    and 0.096 m); with detours the same two holds are reported and end after 1.2 and 1.95 s."""
    from controllers.docking import DockingConfig
    from controllers.scripted import ScriptedController
    from stack.pipeline import ControlStack, StackConfig

    sc = make_scenario("paper-5")
    world = PymunkWorld(sc, ModelError(freeze=(3, 20)))
    state = world.reset(seed=0)
    config = StackConfig(docking=DockingConfig(detour_after_s=1.0 if detour else 0.0))
    watch = HoldWatch(sc.dynamics.dt, sc.target_tolerance, sc.dynamics.accel_limit)
    stack, link = WatchedStack(ControlStack(sc, ScriptedController(sc), config), watch), DroppedFromLink(world, 20, True, 3)
    for step in range(240):
        result = stack.tick(link.view(state))
        world.send_accelerations(link.commands(result.a_cmd, step))
        state = world.step()
    reports = watch.summary()
    held = sorted({r["robot"] for r in reports})
    assert held == ["r2", "r4"], reports
    assert all(r["not_listening"] and r["not_listening"][0][0] == "r3" for r in reports)
    assert len(reports) == 2 and all(r["filter"] == "intervened" for r in reports)
    if detour:
        assert all(r["ended"] and r["seconds"] < 2.5 for r in reports)
    else:
        assert not any(r["ended"] for r in reports) and min(r["seconds"] for r in reports) > 10.0


def test_a_deferred_watch_sees_each_tick_once_and_only_when_asked():
    """`formation bridge` lets the watch look only after a tick's commands went out."""

    class Stack:
        def tick(self, state):
            return _result([[1.0, 0.0], [0, 0]], [[0.0, 0.0], [0, 0]])

    watch = HoldWatch(DT, tolerance=0.05, accel_limit=1.0, hold_s=2 * DT)
    watched = WatchedStack(Stack(), watch, deferred=True)
    state = _state([[0.3, 0.2], [0.8, 0.8]], [[0.5, 0.2], [0.8, 0.8]])
    watched.tick(state)
    watched.tick(state)
    assert watch.summary() == []                         # two ticks, none seen yet
    watched.observe_last()
    watched.observe_last()                               # the same tick again: not counted
    assert watch.summary() == []
    watched.tick(state)
    watched.observe_last()
    assert [r["robot"] for r in watch.summary()] == ["r0"]


def test_a_robot_held_by_a_trackers_obstacle_names_it():
    """Scripted paper-3 with a 5 cm box on the way above the object (the case of
    tests/stack/test_obstacles.py): the robot the filter holds behind it is reported with the
    obstacle named, at its edge."""
    from controllers.scripted import ScriptedController
    from sim.fleet import Obstacles
    from stack.pipeline import ControlStack, StackConfig

    sc = make_scenario("paper-3")
    world = PymunkWorld(sc, ModelError(delay_ticks=2))
    state = world.reset(seed=0)
    watch = HoldWatch(sc.dynamics.dt, sc.target_tolerance, sc.dynamics.accel_limit)
    stack = WatchedStack(ControlStack(sc, ScriptedController(sc), StackConfig()), watch)
    for _ in range(sc.dynamics.episode_steps):
        seen = world.true_state()       # and a tracker's sighting of each robot, on itself
        box = Obstacles(("box", "#r0", "#r1", "#r2"), [[0.5, 0.8], *seen.positions], [0.05, *[0.045] * 3],
                        [0.1, 0.0, 0.0, 0.0], [0.0, *[0.02] * 3], (None, "r0", "r1", "r2"))
        world.send_accelerations(stack.tick(state.replaced(obstacles=box)).a_cmd)
        state = world.step()
    reports = watch.summary()
    assert reports and reports[0]["not_listening"][0][0] == "obstacle box", reports
    assert [name for name, _ in reports[0]["not_listening"]] == ["obstacle box"]   # not a robot's own sighting
    assert 0.04 < reports[0]["not_listening"][0][1] < 0.1
