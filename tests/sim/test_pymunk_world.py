import math

import numpy as np
import pytest
import torch

from sim.fleet import BatchedFleet, Fleet
from sim.geometry import point_polygon_signed_distance_np
from sim.pymunk_world import CollisionCounts, ModelError, PymunkWorld
from sim.scenario import Dynamics, make_scenario, transport_scenario

SC3 = make_scenario("paper-3")
SC5 = make_scenario("paper-5")
ONE = make_scenario("line-1")          # one robot starting at about (0.67, 0.5)
R = SC3.robot_radius

# Agreement of the pymunk world and the batched world without contact (measured: ~4e-15 m).
AGREEMENT_TOL = 1e-12   # [m] and [m/s]


def run(world, commands):
    """Send each (N, 2) command for one tick; return the true (T+1, N, 2) positions and velocities."""
    pos, vel = [world.true_state().positions], [world.true_state().velocities]
    for a in commands:
        world.send_accelerations(a)
        world.step()
        pos.append(world.true_state().positions)
        vel.append(world.true_state().velocities)
    return np.array(pos), np.array(vel)


def constant(a, ticks, n=1):
    return [np.tile(np.asarray(a, dtype=float), (n, 1))] * ticks


# ------------------------------------------------------------------ interface
def test_implements_the_fleet_interface_and_starts_on_jittered_slots():
    world = PymunkWorld(SC3)
    assert isinstance(world, Fleet)
    assert world.dt == 0.05
    s = world.reset(seed=1)
    off = s.positions - SC3.starts
    assert np.all(np.abs(off) <= SC3.start_jitter) and np.any(np.abs(off) > 1e-4)
    jitter = np.random.default_rng(np.random.SeedSequence(1).spawn(4)[0]).uniform(
        -SC3.start_jitter, SC3.start_jitter, (3, 2))
    assert np.array_equal(s.positions, SC3.starts + jitter)
    assert s.step == 0 and s.time == 0.0 and np.all(s.velocities == 0)
    assert np.allclose(s.object_pose, [0.5, 0.5, 0.0]) and np.array_equal(s.targets, SC3.targets)
    s1 = world.step()     # no command sent: zero acceleration, nothing moves
    assert s1.step == 1 and s1.time == pytest.approx(0.05)
    assert np.array_equal(s1.positions, s.positions)


def test_refuses_bad_commands_and_bad_options():
    world = PymunkWorld(SC3)
    with pytest.raises(ValueError, match=r"shape \(num_robots, 2\) = \(3, 2\)"):
        world.send_accelerations(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="NaN or inf"):
        world.send_accelerations(np.array([[np.nan, 0.0]] * 3))
    with pytest.raises(ValueError, match="substeps"):
        PymunkWorld(SC3, substeps=0)
    with pytest.raises(ValueError, match="contact_elasticity"):
        PymunkWorld(SC3, contact_elasticity=1.5)
    with pytest.raises(ValueError, match="positions"):
        world.set_state(np.zeros((2, 2)))


# --------------------------------------------------- agreement with batched
def test_agrees_with_the_batched_world_without_contact():
    """40 ticks in open space: sinusoidal commands (norm 0.8) for four robots, and a fifth pushed
    at 3 m/s^2 (clipped to 1) along x until the speed limit (0.4 m/s) clips, then reversed."""
    open_space = np.array([[0.2, 0.8], [0.5, 0.82], [0.8, 0.8], [0.82, 0.45], [0.2, 0.14]])
    world = PymunkWorld(SC5)
    world.reset(seed=0)
    world.set_state(open_space)
    batched = BatchedFleet(SC5)
    batched.reset(seed=0)
    batched.env.set_state(torch.from_numpy(open_space).unsqueeze(0).clone(),
                          torch.zeros(1, 5, 2, dtype=torch.float64))
    commands = []
    for t in range(40):
        phase = 0.4 * t + 2.0 * np.arange(5)
        a = 0.8 * np.stack((np.cos(phase), np.sin(phase)), -1)
        a[4] = [3.0, 0.0] if t < 14 else [-3.0, 0.0]
        commands.append(a)
    err, top_speed = 0.0, 0.0
    for a in commands:
        world.send_accelerations(a)
        batched.send_accelerations(a)
        sw, sb = world.step(), batched.step()
        assert not world.contacts.any.any()
        err = max(err, np.abs(sw.positions - sb.positions).max(), np.abs(sw.velocities - sb.velocities).max())
        top_speed = max(top_speed, np.linalg.norm(sw.velocities, axis=-1).max())
    assert err < AGREEMENT_TOL
    assert top_speed == pytest.approx(0.4, abs=1e-12)      # the speed clip was exercised
    assert world.collision_counts == CollisionCounts(0, 0, 0)
    assert np.abs(sw.positions - open_space).max() > 0.1     # they really moved


# ---------------------------------------------------------- hand-worked numbers
def test_gain_scales_displacement_from_rest():
    """a = 1 m/s^2 along +y for 4 ticks, c = 0.5, dt = 0.05: q = 1 - c dt = 0.975,
    v_k = dt * (1 + q + ... + q^(k-1)) = 0.05, 0.09875, 0.14628125, 0.19262421875 and
    displacement = dt * sum v_k = 0.0243827734375 m; gain 0.7 gives 0.7 of it."""
    shifts = {}
    for gain in (1.0, 0.7):
        world = PymunkWorld(ONE, ModelError(gain=gain))
        world.reset(seed=0)
        pos, vel = run(world, constant([0.0, 1.0], 4))
        shifts[gain] = pos[-1, 0] - pos[0, 0]
        assert shifts[gain][0] == 0.0
        assert vel[-1, 0, 1] == pytest.approx(gain * 0.19262421875, abs=1e-12)
    assert shifts[1.0][1] == pytest.approx(0.0243827734375, abs=1e-12)
    assert shifts[0.7][1] == pytest.approx(0.7 * 0.0243827734375, abs=1e-12)


@pytest.mark.parametrize("accel, damping, ticks, terminal", [
    (1.0, 0.5, 20, 0.4),    # a / c = 2 m/s > speed_limit 0.4 m/s: the limit holds
    (0.5, 5.0, 40, 0.1),    # a / c = 0.1 m/s < 0.4: damping sets the terminal speed
])
def test_terminal_speed_is_the_lower_of_speed_limit_and_accel_over_damping(accel, damping, ticks, terminal):
    """From rest v_k = (a / c) (1 - q^k), q = 1 - c dt, until the clip: with a = 1, c = 0.5 the
    unclipped v_9 = 2 (1 - 0.975^9) = 0.408 is cut to 0.4, and 0.4 + dt (1 - 0.5 * 0.4) = 0.44 is
    cut again every tick after; with c = 5, v_k = 0.1 (1 - 0.75^k) tends to a / c = 0.1 exactly."""
    sc = transport_scenario(1, dynamics=Dynamics(damping=damping))
    world = PymunkWorld(sc)
    world.reset(seed=0)
    _, vel = run(world, constant([0.0, accel], ticks))       # up along x = 0.67, clear of everything
    speeds = np.linalg.norm(vel, axis=-1)[:, 0]
    k = np.arange(ticks + 1)
    expected = np.minimum(accel / damping * (1 - (1 - damping * 0.05) ** k), 0.4)
    assert np.abs(speeds - expected).max() < 1e-12
    assert speeds[-1] == pytest.approx(terminal, abs=1e-5)   # 0.75^40 * 0.1 = 1e-6
    assert world.collision_counts == CollisionCounts(0, 0, 0)


def test_lag_disturbance_and_floor_friction_by_hand():
    # First-order lag with tau = dt: the applied acceleration after k ticks is 1 - e^-k.
    world = PymunkWorld(ONE, ModelError(lag_tau=0.05))
    world.reset(seed=0)
    applied = []
    for a in constant([0.0, 1.0], 3):
        world.send_accelerations(a)
        world.step()
        applied.append(world.applied_accelerations[0, 1])
    assert applied == pytest.approx([1 - math.exp(-k) for k in (1, 2, 3)], abs=1e-12)

    # A constant disturbance acts like a command: from rest, one tick moves dt^2 * d.
    world = PymunkWorld(ONE, ModelError(disturbance=(0.0, -0.4)))
    s0 = world.reset(seed=0)
    s1 = world.step()
    assert s1.positions[0] - s0.positions[0] == pytest.approx([0.0, -0.4 * 0.05**2], abs=1e-15)

    # Coulomb floor friction 0.3 m/s^2: a push of 0.25 does not move a robot at rest; a push of
    # 0.5 from rest moves it with (0.5 - 0.3) m/s^2 (speed dt * 0.2 = 0.01 m/s after one tick).
    world = PymunkWorld(ONE, ModelError(floor_friction=0.3))
    s0 = world.reset(seed=0)
    pos, _ = run(world, constant([0.0, 0.25], 5))
    assert np.array_equal(pos[-1], s0.positions)
    _, vel = run(world, constant([0.0, 0.5], 1))
    assert vel[-1, 0] == pytest.approx([0.0, 0.01], abs=1e-15)


def test_delay_shifts_the_response_by_k_ticks():
    commands = constant([0.0, 1.0], 6) + constant([0.3, -0.5], 6)
    world = PymunkWorld(ONE)
    world.reset(seed=4)
    base, _ = run(world, commands + constant([0.0, 0.0], 3))
    world = PymunkWorld(ONE, ModelError(delay_ticks=3))
    world.reset(seed=4)
    delayed, _ = run(world, commands + constant([0.0, 0.0], 3))
    assert np.array_equal(delayed[:4], np.repeat(base[:1], 4, axis=0))   # 3 ticks without response
    assert np.abs(delayed[3:] - base[:-3]).max() < 1e-15
    assert np.abs(delayed[6] - base[6]).max() > 1e-3                     # and the shift matters



def test_each_state_counts_the_commands_sent_after_the_one_the_robot_acted_on():
    """``commands_pending`` as a STATE's ``last_cmd_seq`` gives it: the delay in ticks once
    commands flow (1-3 on a jittering link, exactly 3 behind a 3-tick playout buffer); a dropped
    state carries the count of when it was measured plus the ticks it aged; a frozen robot acts
    on nothing new, so its count grows by one a tick."""
    zero = np.zeros((3, 2))

    def counts(model_error, ticks=8):
        world = PymunkWorld(SC3, model_error)
        state, out = world.reset(seed=2), []
        for _ in range(ticks):
            world.send_accelerations(zero)
            state = world.step()
            out.append((state.commands_pending.tolist(), state.ages().round(9).tolist()))
        return out

    assert [c for c, _ in counts(ModelError(delay_ticks=2))] == [[1] * 3] + [[2] * 3] * 7
    dropped = counts(ModelError(delay_ticks=1, state_drop=0.5), ticks=30)
    aged = [(step + 1 - round(a / SC3.dynamics.dt), p - round(a / SC3.dynamics.dt))
            for step, (c, ages) in enumerate(dropped) for p, a in zip(c, ages, strict=True)]
    assert {delay for measured_at, delay in aged if measured_at >= 1} == {1}   # after the first command
    assert max(a for _, ages in dropped for a in ages) > 0          # some states did drop
    jitter = dict(delay_ticks=1, delay_jitter_ticks=2)
    datagrams = [c for c, _ in counts(ModelError(**jitter), ticks=40)][5:]
    assert {p for c in datagrams for p in c} == {1, 2, 3}
    buffered = [c for c, _ in counts(ModelError(**jitter, playout_ticks=3), ticks=40)][5:]
    assert {p for c in buffered for p in c} == {3}              # the playout buffer: exactly 3
    frozen = counts(ModelError(freeze=(1, 3)))
    assert [c[1] for c, _ in frozen] == [0, 0, 1, 2, 3, 4, 5, 6]      # silent from the state of tick 3
    assert [c[0] for c, _ in frozen] == [0] * 8



def test_a_frozen_robot_must_be_one_of_the_team():
    with pytest.raises(ValueError, match=r"freeze.*robot row 3, but paper-3 has 3 robots: pick a row in 0\.\.2"):
        PymunkWorld(SC3, ModelError(freeze=(3, 10)))
    assert PymunkWorld(SC3, ModelError(freeze=(2, 10))).reset(seed=0).positions.shape == (3, 2)


def test_an_adaptive_playout_buffer_fixes_a_jittering_delay_at_its_maximum_and_adds_none():
    """adaptive_playout: once robot i has seen a 3-tick delay it acts on every command 3 ticks
    after the tick it answers (the count is 3 for good); on a constant 2-tick link it changes
    nothing, to the bit."""
    def run(model_error, ticks=40):
        world = PymunkWorld(SC3, model_error)
        world.reset(seed=4)
        rng, out = np.random.default_rng(0), []
        for _ in range(ticks):
            world.send_accelerations(rng.uniform(-0.3, 0.3, (3, 2)))
            state = world.step()
            out.append((state.commands_pending.tolist(), world.true_state().positions.copy()))
        return out

    jitter = run(ModelError(delay_ticks=1, delay_jitter_ticks=2, adaptive_playout=True))
    counts = np.array([c for c, _ in jitter])                     # (ticks, robots)
    first3 = [int(np.argmax(counts[:, i] == 3)) for i in range(3)]
    assert all(f < 15 for f in first3)
    assert all((counts[f:, i] == 3).all() for i, f in enumerate(first3))   # then exactly 3
    newest = np.array([c for c, _ in run(ModelError(delay_ticks=1, delay_jitter_ticks=2))])
    assert set(newest[15:].ravel()) == {1, 2, 3}                  # acting on arrival: 1-3
    plain, adaptive = run(ModelError(delay_ticks=2)), run(ModelError(delay_ticks=2, adaptive_playout=True))
    assert [c for c, _ in plain] == [c for c, _ in adaptive]
    assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(plain, adaptive, strict=True))


# ------------------------------------------------------------- randomness
ALL_ERRORS = ModelError(gain=0.85, gain_spread=0.15, lag_tau=0.1, delay_ticks=1, disturbance=(0.05, -0.02),
                        disturbance_std=0.1, floor_friction=0.05, position_noise_std=0.002,
                        velocity_noise_std=0.01)


def test_same_seed_repeats_exactly_and_different_seeds_differ():
    commands = [np.tile([0.2 * math.cos(0.2 * t), 0.4], (3, 1)) for t in range(20)]

    def episode(seed):
        world = PymunkWorld(SC3, ALL_ERRORS)
        world.reset(seed=seed)
        measured = []
        for a in commands:
            world.send_accelerations(a)
            s = world.step()
            measured.append(np.concatenate((s.positions, s.velocities)))
        return np.array(measured), world.true_state().positions, world.gains

    m1, t1, g1 = episode(7)
    m2, t2, g2 = episode(7)
    m3, t3, g3 = episode(8)
    assert np.array_equal(m1, m2) and np.array_equal(t1, t2) and np.array_equal(g1, g2)
    assert np.abs(m1 - m3).max() > 1e-3 and np.abs(t1 - t3).max() > 1e-4
    assert np.all((g1 >= 0.7) & (g1 <= 1.0)) and np.ptp(g1) > 0 and not np.array_equal(g1, g3)


def test_reset_without_seed_continues_the_streams():
    world = PymunkWorld(SC3, seed=3)
    first = world.reset().positions
    second = world.reset().positions
    assert not np.array_equal(first, second)
    again = PymunkWorld(SC3, seed=3)
    assert np.array_equal(again.reset().positions, first)


def test_measurement_noise_changes_read_state_but_not_true_state():
    commands = constant([0.1, 0.3], 30, n=3)
    clean = PymunkWorld(SC3)
    clean.reset(seed=5)
    noisy = PymunkWorld(SC3, ModelError(position_noise_std=0.002, velocity_noise_std=0.01))
    noisy.reset(seed=5)
    dp, dv = [], []
    for a in commands:
        for w in (clean, noisy):
            w.send_accelerations(a)
            w.step()
        assert np.array_equal(noisy.true_state().positions, clean.true_state().positions)
        assert np.array_equal(noisy.true_state().velocities, clean.true_state().velocities)
        measured = noisy.read_state()
        dp.append(measured.positions - noisy.true_state().positions)
        dv.append(measured.velocities - noisy.true_state().velocities)
    assert np.array_equal(noisy.read_state().positions, measured.positions)   # one draw per tick
    # 180 draws each: sample std within 20 % of the set std (chi-square 5-sigma is about 13 %).
    assert np.std(dp) == pytest.approx(0.002, rel=0.2)
    assert np.std(dv) == pytest.approx(0.01, rel=0.2)
    assert np.array_equal(clean.read_state().positions, clean.true_state().positions)


# ------------------------------------------------------------- contacts
def _min_gap(positions):
    """Smallest centre distance between two robots over a (T, N, 2) trajectory."""
    d = np.linalg.norm(positions[:, :, None] - positions[:, None], axis=-1)
    d[:, np.arange(d.shape[1]), np.arange(d.shape[1])] = np.inf
    return d.min()


def test_robot_driven_into_a_wall_is_stopped_and_counted():
    world = PymunkWorld(ONE)
    world.reset(seed=0)
    pos, _ = run(world, constant([1.0, 0.0], 40))          # from x = 0.67 towards x = 1
    assert pos[:, 0, 0].max() <= 1.0 - R + 2e-3            # overlap below 2 mm, never through
    assert world.contacts.wall[0] and not world.contacts.object[0]
    counts = world.collision_counts
    assert counts.wall == 1 and counts.robot == 0 and counts.object == 0 and counts.any
    assert not world.outcome().success[0]


def test_robots_driven_into_each_other_are_stopped_and_counted():
    """Robots 0 and 1 (y = 0.375, 0.5 at x = 0.67) pushed towards each other at 1 m/s^2."""
    commands = [np.array([[0.0, 1.0], [0.0, -1.0], [0.0, 0.0]])] * 20
    world = PymunkWorld(SC3)
    start = world.reset(seed=0)
    pos, _ = run(world, commands)
    assert _min_gap(pos) >= 2 * R - 2e-3
    assert world.collision_counts.robot >= 2 and world.collision_counts.wall == 0
    hit = [world.contacts.robot.copy()]
    assert hit[0][0] and hit[0][1] and not hit[0][2]
    # Teeth: the batched world has no contact forces and lets the same robots pass into each other.
    batched = BatchedFleet(SC3)
    batched.reset(seed=0)
    batched.env.set_state(torch.from_numpy(start.positions).unsqueeze(0).clone(),
                          torch.zeros(1, 3, 2, dtype=torch.float64))
    ghost = [start.positions]
    for a in commands:
        batched.send_accelerations(a)
        ghost.append(batched.step().positions)
    assert _min_gap(np.array(ghost)) < 2 * R - 0.03


def test_robot_driven_into_the_object_is_stopped_and_the_object_stays():
    world = PymunkWorld(ONE)
    world.reset(seed=0)
    pos, _ = run(world, constant([-1.0, 0.0], 30))         # from x = 0.67 towards the edge x = 0.6
    clearance = point_polygon_signed_distance_np(pos[:, 0], ONE.polygon)
    assert clearance.min() >= R - 2e-3
    assert world.contacts.object[0] and world.collision_counts.object == 1
    assert world.collision_counts.wall == 0 and world.collision_counts.robot == 0
    assert np.allclose(world.read_state().object_pose, [0.5, 0.5, 0.0], atol=1e-12)


def test_non_convex_object_blocks_robots_in_its_notch():
    """An L-shaped object (notch at the upper right): a robot driven into the notch corner stops."""
    ell = ((0.3, 0.3), (0.7, 0.3), (0.7, 0.45), (0.45, 0.45), (0.45, 0.7), (0.3, 0.7))
    sc = transport_scenario(1, object_vertices=ell)
    world = PymunkWorld(sc)
    world.reset(seed=0)
    world.set_state(np.array([[0.6, 0.6]]))
    pos, _ = run(world, constant([-0.7, -0.7], 30))
    assert point_polygon_signed_distance_np(pos[:, 0], sc.polygon).min() >= R - 2e-3
    assert world.contacts.object[0]


def test_outcome_of_a_robot_left_at_rest():
    world = PymunkWorld(ONE)
    s = world.reset(seed=2)
    out = world.outcome()
    expected = np.linalg.norm(s.positions[0] - ONE.targets[0])     # about 0.34 m: not arrived
    assert float(out.final_distance[0]) == pytest.approx(expected, abs=1e-12)
    assert not out.success[0]
    world.set_state(ONE.targets + 0.01)                               # 0.0141 m < tolerance 0.05
    assert world.outcome().success[0]


def test_a_reset_after_an_episode_in_contact_leaves_robots_at_rest():
    """Robots rammed into the right wall for 60 ticks, then a new episode: at rest on their start
    slots, under a zero command, nothing may move (before, Chipmunk's correction velocity of the
    last contact moved every robot 21.6 um in the first tick)."""
    scenario = make_scenario("paper-3")
    world = PymunkWorld(scenario, ModelError())
    world.reset(seed=0)
    for _ in range(60):
        world.send_accelerations(np.tile([1.0, 0.0], (3, 1)))
        world.step()
    assert world.collision_counts.wall == 3
    start = world.reset(seed=1)
    world.send_accelerations(np.zeros((3, 2)))
    assert np.array_equal(world.step().positions, start.positions)


def test_a_contact_pymunk_resolves_within_one_tick_is_a_collision():
    """Collisions were judged from the positions at the end of each tick only: a robot grazing
    the box's top edge 1 mm deep was pushed out within the tick's substeps and nothing was
    counted; a robot dashing past a neighbour shoved it 24 mm off its slot and the episode
    read as a success. Both are counted now, as the batched world counts them."""
    from sim.scenario import make_scenario

    sc = make_scenario("transport-2")
    world = PymunkWorld(sc)
    world.reset(seed=0)
    world.set_state(np.array([[0.30, 0.689], [0.2, 0.2]]), np.array([[0.4, 0.0], [0.0, 0.0]]))
    touched = []
    for _ in range(8):                   # along the top edge (y = 0.65), the centre 39 mm above it
        world.send_accelerations(np.array([[1.0, 0.0], [0.0, 0.0]]))
        world.step()
        touched.append(bool(world.contacts.object[0]))
    assert any(touched) and world.collision_counts.object == 1 and world.collision_counts.robot == 0

    targets = sc.targets
    world = PymunkWorld(sc)
    world.reset(seed=0)
    world.set_state(np.array([[targets[0, 0] - 0.065, 0.085], targets[0]]))
    for _ in range(sc.dynamics.episode_steps):
        state = world.true_state()
        pos, vel = state.positions, state.velocities
        accel = 4.0 * (targets[[1, 0]] - pos) - 3.0 * vel   # robot 0 to the upper target past robot 1
        if pos[0, 1] < targets[0, 1] + 0.06:
            accel[0] = (0.0, 1.0)
        world.send_accelerations(accel)
        world.step()
    assert world.collision_counts.robot == 2 and not world.outcome().success[0]
