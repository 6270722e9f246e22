"""Silent robots in the policy's and docking's view (stack/team_view.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

from sim.fleet import FleetState, SilentRobots
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import make_scenario, transport_scenario
from stack.pipeline import ControlStack, StackConfig
from stack.team_view import team_view


def fleet_state(silent: SilentRobots | None) -> FleetState:
    return FleetState(time=1.0, step=20, positions=[[0.1, 0.2], [0.3, 0.4]], velocities=[[0.0, 0.1], [0.2, 0.0]],
                      targets=[[0.2, 0.5], [0.2, 0.6]], object_pose=[0.5, 0.5, 0.0], robot_ids=("a", "b"),
                      state_age_s=[0.05, 0.1], silent=silent, commands_pending=np.array([1, 0]))


def test_silent_robots_with_targets_join_the_team_after_the_rows():
    silent = SilentRobots(("c",), [[0.7, 0.8]], [[0.0, -0.2]], [0.7], targets=[[0.2, 0.7]])
    team = team_view(fleet_state(silent), None)
    np.testing.assert_array_equal(team.positions, [[0.1, 0.2], [0.3, 0.4], [0.7, 0.8]])
    np.testing.assert_array_equal(team.velocities, [[0.0, 0.1], [0.2, 0.0], [0.0, -0.2]])
    np.testing.assert_array_equal(team.targets, [[0.2, 0.5], [0.2, 0.6], [0.2, 0.7]])
    assert team.robot_ids == ("a", "b", "c")
    np.testing.assert_array_equal(team.ages(), [0.05, 0.1, 0.7])
    np.testing.assert_array_equal(team.pending(), [1, 0, -1])
    assert team.silent is None
    counted = SilentRobots(("c",), [[0.7, 0.8]], [[0.0, -0.2]], [0.7], targets=[[0.2, 0.7]],
                           commands_pending=np.array([5]))
    np.testing.assert_array_equal(team_view(fleet_state(counted), None).pending(), [1, 0, 5])
    unknown = team_view(fleet_state(SilentRobots(("c",), [[0.7, 0.8]], [[0.0, -0.2]], [0.7])), None)
    assert unknown.robot_ids == ("a", "b") and unknown.num_robots == 2


@pytest.mark.parametrize("targets, message", [([[0.2, 0.7], [0.1, 0.1]], r"targets must have shape \(1, 2\)"),
                                              ([[np.nan, 0.7]], "targets must be finite")])
def test_silent_targets_are_checked_by_name(targets, message):
    with pytest.raises(ValueError, match=message):
        SilentRobots(("c",), [[0.7, 0.8]], [[0.0, -0.2]], [0.7], targets=targets)


@pytest.mark.parametrize("pending", [np.array([3, 4]), np.array([-2]), np.array([1.5])])
def test_silent_pending_counts_are_checked_by_name(pending):
    with pytest.raises(ValueError, match=r"SilentRobots.commands_pending must be 1 integers >= 0 \(-1: unknown\)"):
        SilentRobots(("c",), [[0.7, 0.8]], [[0.0, -0.2]], [0.7], commands_pending=pending)


class DroppedFromLink:
    """A pymunk fleet whose link drops robot ``robot`` from ``drop`` on, as the bridge does when
    its token lapses: no longer a row, but a silent robot with its last state, that state's age
    and (with ``targets``) its target.

    ``pending``: the silent robot's ``commands_pending``: "unknown" (-1), "counted" as the bridge
    counts it (its count at its last row, plus the ticks since: the controller records a braking
    row for it on each), or "zero" (no command in flight, wrongly where the world delays them)."""

    def __init__(self, world: PymunkWorld, drop: int, targets: bool, robot: int = 0, pending: str = "unknown"):
        self.world, self.drop, self.targets, self.robot, self.last = world, drop, targets, robot, None
        self.pending = pending

    def view(self, state: FleetState) -> FleetState:
        k = self.robot
        if state.step < self.drop:
            self.last = (state.positions[k].copy(), state.velocities[k].copy(), state.time - state.ages()[k],
                         int(state.pending()[k]), state.step)
            return state
        pos, vel, measured, count, step = self.last
        rows = np.arange(state.num_robots) != k
        pending = {"unknown": -1, "counted": count + state.step - step, "zero": 0}[self.pending]
        silent = SilentRobots((state.robot_ids[k],), pos[None], vel[None], [state.time - measured],
                              targets=state.targets[k:k + 1] if self.targets else None,
                              commands_pending=np.array([pending]))
        return FleetState(time=state.time, step=state.step, positions=state.positions[rows],
                          velocities=state.velocities[rows], targets=state.targets[rows],
                          object_pose=state.object_pose, robot_ids=tuple(np.array(state.robot_ids)[rows]),
                          state_age_s=state.ages()[rows], silent=silent,
                          commands_pending=None if state.commands_pending is None else state.commands_pending[rows])

    def commands(self, rows: np.ndarray, step: int) -> np.ndarray:
        """The (N, 2) command the fleet gets from a stack's rows (the dropped robot's: 0)."""
        if step < self.drop:
            return rows
        out = np.zeros((len(rows) + 1, 2))
        out[np.arange(len(out)) != self.robot] = rows
        return out


class PushFirstRow(torch.nn.Module):
    """A network for any N that drives its first row at full thrust along ``push`` and leaves
    the others at rest."""

    obs_kind = "tokens"
    num_robots = -1

    def __init__(self, push: np.ndarray):
        super().__init__()
        self.register_buffer("push", torch.as_tensor(push, dtype=torch.float32))

    def forward(self, obs: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        out = torch.zeros(obs.shape[0], obs.shape[1], 2)
        out[:, 0] = self.push
        return out


def seen_by_policy(stack: ControlStack) -> list[dict[str, np.ndarray]]:
    """Record, per tick, each robot id's position in the fleet state the policy is given."""
    seen, policy = [], stack._policy

    def recorded(state, t0):
        seen.append(dict(zip(state.robot_ids, state.positions.copy(), strict=True)))
        return policy(state, t0)

    stack._policy = recorded
    return seen


@pytest.mark.parametrize("targets", [True, False])
def test_a_robot_dropped_from_the_link_is_seen_where_a_stale_row_is_seen(targets):
    """Robot 0 of paper-3 is pushed away from the object at full thrust and freezes at tick 10
    at the speed limit; it counts as stale from tick 12, when a second link drops it (silent,
    with its last state). A policy for any N fed the dropped robot's fleet sees it, from the tick
    after, where the stack fed the full fleet sees the stale row: where it must have stopped, not
    where it last reported itself (the same to 1e-12 m; both links without pending counts). Its
    target unknown, the policy does not see it at all."""
    sc = make_scenario("paper-3")
    world = PymunkWorld(sc, ModelError(freeze=(0, 10)))
    state = world.reset(seed=0)
    away = state.positions[0] - state.object_pose[:2]
    policy = PushFirstRow(away / np.linalg.norm(away))
    full, dropped = ControlStack(sc, policy), ControlStack(sc, policy)
    seen_full, seen_dropped = seen_by_policy(full), seen_by_policy(dropped)
    link = DroppedFromLink(world, drop=12, targets=targets)
    for _ in range(30):
        state = state.replaced(commands_pending=None)   # a silent robot's pending count is unknown
        result = full.tick(state)
        dropped.tick(link.view(state))
        world.send_accelerations(result.a_cmd)
        state = world.step()
    assert not result.stale[1:].any() and result.stale[0]
    for k in range(13, 30):
        if targets:
            assert set(seen_dropped[k]) == {"r0", "r1", "r2"}
            np.testing.assert_allclose(seen_dropped[k]["r0"], seen_full[k]["r0"], rtol=0, atol=1e-12)
        else:
            assert set(seen_dropped[k]) == {"r1", "r2"}
    rest = world.true_state().positions[0]
    assert np.linalg.norm(seen_full[-1]["r0"] - rest) < 0.02 < np.linalg.norm(link.last[0] - rest)


@pytest.mark.parametrize("targets", [True, False])
def test_docking_judges_a_target_by_a_dropped_robot_as_by_a_stale_row(targets):
    """Robot 0 crosses above the object at full thrust and freezes at tick 25, 49 mm from robot
    1's target; it counts as stale from tick 27, when a second link drops it. Robot 1 (its
    policy a plain callable, which keeps its rows) docks from tick 28 in both stacks: docking
    sees the dropped robot where the first stack sees the stale row. Its target unknown, the
    dropped robot is not in docking's view and robot 1 docks a tick earlier, at 27."""
    from sim.scenario import Scenario
    sc = Scenario(name="dock-beside-a-frozen-robot", num_robots=2, start_slots=((0.9, 0.74), (0.5, 0.85)),
                  target_slots=((0.3, 0.8), (0.5, 0.8)), start_jitter=0.0)
    world = PymunkWorld(sc, ModelError(freeze=(0, 25)))
    state = world.reset(seed=0)

    def policy(s: FleetState) -> np.ndarray:
        return np.array([[-1.0, 0.0] if rid == "r0" else [0.0, 0.0] for rid in s.robot_ids])

    full, dropped = ControlStack(sc, policy), ControlStack(sc, policy)
    link = DroppedFromLink(world, drop=27, targets=targets)
    docked_full, docked_dropped = [], []
    for _ in range(60):
        result = full.tick(state)
        docked_full.append(bool(result.docking[1]))
        docked_dropped.append(bool(dropped.tick(link.view(state)).docking[-1]))
        world.send_accelerations(result.a_cmd)
        state = world.step()
    assert docked_full.index(True) == 28 and all(docked_full[28:])
    assert docked_dropped.index(True) == (28 if targets else 27)


@pytest.mark.parametrize("detour", [True, False])
def test_a_robot_held_behind_a_dropped_robot_is_led_round_it(detour):
    """Scripted paper-5: robot 3 freezes at tick 20 on its way above the object and its link
    drops it. The scripted controller drives robots 2 and 4 straight at their slots, into the
    filter's bound round robot 3, and without detours both stand there to the end (tick 240),
    over 0.3 m from any free target. Held still for a second, each is led round on a grid path:
    robot 4 ends on a target; robot 2 gets round too (tick 171), but its controller, which is
    not given robot 3's slot, drives it back along the top of the object, where it is held
    again (a new plan at tick 238).
    Nobody touches anything either way."""
    from controllers.docking import DockingConfig
    from controllers.scripted import ScriptedController
    from stack.pipeline import StackConfig
    sc = make_scenario("paper-5")
    world = PymunkWorld(sc, ModelError(freeze=(3, 20)))
    state = world.reset(seed=0)
    config = StackConfig(docking=DockingConfig(detour_after_s=1.0 if detour else 0.0))
    stack, link, detoured = ControlStack(sc, ScriptedController(sc), config), DroppedFromLink(world, 20, True, 3), []
    for step in range(240):
        result = stack.tick(link.view(state))
        detoured.append(bool(result.detour.any()))
        world.send_accelerations(link.commands(result.a_cmd, step))
        state = world.step()
    others = world.true_state().positions[[0, 1, 2, 4]]
    gaps = np.linalg.norm(others[:, None] - sc.targets[None], axis=2)
    off = gaps[linear_sum_assignment(gaps)]                  # each robot to a target of its own
    assert world.collision_counts.robot == world.collision_counts.object == world.collision_counts.wall == 0
    if detour:
        assert np.count_nonzero(off < 0.01) == 3 and any(detoured)
    else:
        assert np.count_nonzero(off < 0.01) == 2 and np.sort(off)[-2:].min() > 0.3 and not any(detoured)



def _thrust_and_drop(pending: str, goal: tuple[float, float] | None, ticks: int) -> tuple:
    """Robot 0 thrusts along +x, asked a sideways push that alternates (+-0.8 m/s^2: commands
    that differ from tick to tick), through a world that delays every command two ticks; it
    freezes at tick 12 at the speed limit (silent and deaf, holding its push two ticks, then its
    watchdog brakes it) and the link drops it at once. Robot 1 is driven by a PD law to ``goal``
    (None: it stays at rest, far off). Returns ``(regions, truth, gap, end)``: from the drop on,
    the discs (centres (C, 2), radii (C,) [m]) the filter kept round robot 0 at each tick, robot
    0's true centre after each tick, the smallest gap between the robots [m] and robot 1's final
    distance to ``goal`` [m]."""
    sc = transport_scenario(2)
    world = PymunkWorld(sc, ModelError(freeze=(0, 12), delay_ticks=2))
    world.reset(seed=0)
    world.set_state(np.array([[0.1, 0.85], [0.35, 0.7 if goal else 0.4]]), np.zeros((2, 2)))
    state, aim = world.read_state(), np.array(goal or (0.35, 0.4))

    def policy(s: FleetState) -> np.ndarray:
        return np.array([[1.0, 0.8 * (-1) ** s.step] if rid == "r0" else 4.0 * (aim - p) - 3.0 * v
                         for rid, p, v in zip(s.robot_ids, s.positions, s.velocities, strict=True)])

    stack, link = ControlStack(sc, policy), DroppedFromLink(world, 12, targets=False, pending=pending)
    regions, truth, gap, predict = [], [], np.inf, stack.predictor.predict

    def kept(*args, **kwargs):
        p = predict(*args, **kwargs)
        covers = [(c, r) for row, c, r in p.covers if row == 1]
        regions.append(covers[0] if covers else (p.pos[1][None], p.grow[1:2]))
        return p

    stack.predictor.predict = kept
    for step in range(ticks):
        result = stack.tick(link.view(state))
        world.send_accelerations(link.commands(result.a_cmd, step))
        state = world.step()
        true = world.true_state().positions
        truth.append(true[0].copy())
        gap = min(gap, float(np.linalg.norm(true[0] - true[1])) - 2 * sc.robot_radius)
    return regions[12:], truth[12:], gap, float(np.linalg.norm(true[1] - aim))


@pytest.mark.parametrize("pending", ["counted", "zero", "unknown"])
def test_a_dropped_robot_counted_as_the_bridge_counts_it_lies_in_a_small_cover(pending):
    """Robot 0 drops off the link at full speed with two commands in flight (:func:`_thrust_and_drop`).
    Counted as the bridge counts it, its disc and then its cover (discs of 34 mm once it is at
    rest) hold its true centre at every tick they are predicted for (the filter's command acts
    three ticks on, its latency bound); counted as if nothing were in flight, they miss it on 40
    or more ticks (by 13 mm); unknown, they hold it, but the cover's discs are 229 mm, seven
    times as wide: every count the delay bound allows is a branch, and the spread of its
    commands counts in full."""
    regions, truth, _, _ = _thrust_and_drop(pending, None, 60)
    ahead = int(round(StackConfig().latency.command_delay_s / 0.05))
    misses = sum((np.linalg.norm(truth[k + ahead - 1] - centres, axis=1) - radii).min() > 1e-9
                 for k, (centres, radii) in enumerate(regions[:-ahead]))
    at_rest = float(regions[-1][1].max())
    if pending == "counted":
        assert misses == 0 and at_rest < 0.04
    elif pending == "zero":
        assert misses >= 40
    else:
        assert misses == 0 and at_rest > 0.2


def test_a_neighbour_reaches_its_goal_beside_a_dropped_robot_counted_as_the_bridge_counts_it():
    """Robot 1 drives to a goal 90 mm below where the dropped robot 0 comes to rest
    (:func:`_thrust_and_drop`). With robot 0's commands counted it ends 5 mm from its goal; with
    the count unknown the disc round robot 0 keeps it 78 mm off. Neither touches robot 0."""
    near, gap_near = _thrust_and_drop("counted", (0.305, 0.763), 100)[2:][::-1]
    far, gap_far = _thrust_and_drop("unknown", (0.305, 0.763), 100)[2:][::-1]
    assert near < 0.006 and far > 0.07
    assert gap_near > 0.03 and gap_far > 0.03


@pytest.mark.parametrize("variant", ["slot", "mlp"])
def test_a_network_of_a_fixed_team_size_runs_the_team_with_a_robot_off_the_link(variant):
    """A 5-robot slot or MLP actor from a checkpoint was handed the 4 rows left when r3 dropped
    off the link (its exported file got the team of 5): tick raised on every tick the robot was
    away, and the bridge braked the whole fleet."""
    from controllers.policy import ActorConfig, build_actor

    sc = make_scenario("paper-5")
    torch.manual_seed(0)
    net = build_actor(ActorConfig(variant=variant, embed_dim=16, num_heads=2, hidden_sizes=(32,)), 5).eval()
    stack = ControlStack(sc, net)
    full = PymunkWorld(sc).reset(seed=0)
    stack.tick(full)
    keep = [0, 1, 2, 4]
    state = FleetState(time=full.time + 0.05, step=1, positions=full.positions[keep],
                       velocities=full.velocities[keep], targets=full.targets[keep], object_pose=full.object_pose,
                       robot_ids=tuple(full.robot_ids[i] for i in keep), state_age_s=np.zeros(4),
                       commands_pending=np.ones(4, dtype=np.int64),
                       silent=SilentRobots(("r3",), full.positions[[3]], full.velocities[[3]], np.array([0.05]),
                                           full.targets[[3]], np.array([1])))
    result = stack.tick(state)
    assert result.policy_status == "ok" and result.a_cmd.shape == (4, 2) and np.isfinite(result.a_cmd).all()


def test_a_new_robots_non_finite_row_leaves_no_nan_disc_for_the_detour_of_the_next_tick():
    """A robot never seen before that reports NaN is handled on its tick (nobody moves), but its
    disc stayed in that tick's prediction with a NaN centre, and a detour planned on the next
    tick read it: math.floor(NaN) raised out of tick()."""
    from controllers.scripted import ScriptedController

    sc = make_scenario("paper-5")
    world = PymunkWorld(sc, ModelError(freeze=(3, 20)))
    state = world.reset(seed=0)
    stack, link = ControlStack(sc, ScriptedController(sc), StackConfig()), DroppedFromLink(world, 20, True, 3)
    plans, plan = [], stack.detour.plan
    stack.detour.plan = lambda *a, **k: plans.append(step) or plan(*a, **k)
    for step in range(52):
        view = link.view(state)
        newcomer = step == 49                  # a replan tick (detours plan at 39, 49, ...)
        if newcomer:
            view = FleetState(time=view.time, step=view.step, positions=np.vstack([view.positions, [np.nan, np.nan]]),
                              velocities=np.vstack([view.velocities, [0.0, 0.0]]),
                              targets=np.vstack([view.targets, [0.5, 0.9]]), object_pose=view.object_pose,
                              robot_ids=view.robot_ids + ("x9",), state_age_s=np.append(view.ages(), 0.0),
                              silent=view.silent)
        result = stack.tick(view)
        assert np.isfinite(result.a_cmd).all()
        world.send_accelerations(link.commands(result.a_cmd[:-1] if newcomer else result.a_cmd, step))
        state = world.step()
    assert 50 in plans                          # the detour did plan on the tick after the NaN row


def test_detours_still_lead_a_robot_home_with_dockings_second_tier_off():
    """DockingConfig(stall_radius=0) turns docking's second tier off; the detour planner took the
    same radius as its goal tolerance, found no path to any goal and detours stopped silently
    (2 of 4 robots home instead of 3). A detour now ends within capture_radius then."""
    from controllers.docking import DockingConfig
    from controllers.scripted import ScriptedController

    sc = make_scenario("paper-5")
    world = PymunkWorld(sc, ModelError(freeze=(3, 20)))
    state = world.reset(seed=0)
    cfg = StackConfig(docking=DockingConfig(detour_after_s=1.0, stall_radius=0.0))
    stack, link, detoured = ControlStack(sc, ScriptedController(sc), cfg), DroppedFromLink(world, 20, True, 3), 0
    for step in range(240):
        result = stack.tick(link.view(state))
        detoured += int(result.detour.any())
        world.send_accelerations(link.commands(result.a_cmd, step))
        state = world.step()
    others = world.true_state().positions[[0, 1, 2, 4]]
    gaps = np.linalg.norm(others[:, None] - sc.targets[None], axis=2)
    off = gaps[linear_sum_assignment(gaps)]
    assert detoured > 0 and np.count_nonzero(off < 0.01) >= 3, (detoured, off)
