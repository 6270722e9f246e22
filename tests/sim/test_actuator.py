"""The batched world's actuator model (gain, lag, delay) against hand-worked numbers and pymunk."""

import math

import numpy as np
import pytest
import torch

from sim.batched_env import BatchedFormationEnv
from sim.distribution import ScenarioDistribution
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import make_scenario

SC = make_scenario("paper-3")
OPEN = np.array([[0.2, 0.15], [0.5, 0.15], [0.8, 0.15]])   # clear of each other, the box and the walls
DRAWN = ScenarioDistribution(gain=(0.5, 1.5), lag_tau=(0.0, 0.2), delay_ticks=(0, 3))


def _env(e: int, distribution=DRAWN) -> BatchedFormationEnv:
    env = BatchedFormationEnv(SC, e, seed=0, dtype=torch.float64, distribution=distribution)
    env.reset()
    pos = torch.from_numpy(OPEN).expand(e, -1, -1).clone()
    env.set_state(pos, torch.zeros_like(pos))
    return env


def _set(env, gain, alpha, delay):
    ids = torch.arange(env.num_envs)
    env.actuators.reset(ids, np.repeat(np.asarray(gain, float)[:, None], 3, 1),
                        np.asarray(alpha, float), np.asarray(delay))


def test_gain_lag_and_delay_by_hand():
    """Env 0: gain 0.5; env 1: delay 2 ticks; env 2: lag alpha 0.25. One robot pushed at 1 m/s^2."""
    env = _env(3)
    _set(env, [0.5, 1.0, 1.0], [1.0, 1.0, 0.25], [0, 2, 0])
    push = torch.zeros(3, 3, 2, dtype=torch.float64)
    push[:, 0, 0] = 1.0
    vx = []
    for _ in range(3):
        env.step(push)
        vx.append(env.vel[:, 0, 0].tolist())
    vx = np.array(vx)                                             # (step, env)
    c, dt = SC.dynamics.damping, SC.dynamics.dt
    # gain 0.5: v1 = dt * 0.5
    assert vx[0, 0] == pytest.approx(dt * 0.5)
    # delay 2: nothing for two steps, then the first command: v3 = dt * 1
    assert vx[0, 1] == 0.0 and vx[1, 1] == 0.0 and vx[2, 1] == pytest.approx(dt)
    # lag: a1 = 0.25, a2 = 0.25 + 0.25 * 0.75 = 0.4375; v2 = v1 + dt (a2 - c v1)
    v1 = dt * 0.25
    assert vx[0, 2] == pytest.approx(v1)
    assert vx[1, 2] == pytest.approx(v1 + dt * (0.4375 - c * v1))


@pytest.mark.parametrize("me", [ModelError(gain=0.7), ModelError(lag_tau=0.1), ModelError(delay_ticks=2),
                                ModelError(gain=1.2, lag_tau=0.05, delay_ticks=3)])
def test_agrees_with_pymunk_model_error_without_contact(me):
    """30 ticks of sinusoidal commands (norm 0.6) in open space: the batched world with the same knobs moves
    the robots as pymunk's ModelError does, to rounding."""
    env = _env(1)
    alpha = 1.0 if me.lag_tau == 0 else 1.0 - math.exp(-SC.dynamics.dt / me.lag_tau)
    _set(env, [me.gain], [alpha], [me.delay_ticks])
    world = PymunkWorld(SC, me)
    world.reset(seed=0)
    world.set_state(OPEN)
    err = 0.0
    for t in range(30):
        phase = 0.4 * t + 2.0 * np.arange(3)
        a = 0.6 * np.stack((np.cos(phase), np.sin(phase)), -1)
        world.send_accelerations(a)
        world.step()
        env.step(torch.from_numpy(a).unsqueeze(0))
        assert not world.contacts.any.any()
        err = max(err, np.abs(world.true_state().positions - env.pos[0].numpy()).max())
    assert err < 1e-12
    assert np.abs(world.true_state().positions - OPEN).max() > 0.02       # they moved


def test_a_reset_empties_the_delay_line_and_the_actuator():
    env = _env(2)
    _set(env, [1.0, 1.0], [0.5, 0.5], [2, 2])
    push = torch.ones(2, 3, 2, dtype=torch.float64)
    for _ in range(4):
        env.step(push)
    assert env.actuators.act[0].abs().max() > 0.5
    env.reset(env_ids=torch.tensor([0]))
    assert env.actuators.act[0].abs().max() == 0 and env.actuators.act[1].abs().max() > 0.5
    assert env.actuators.line[:, 0].abs().max() == 0
    _set(env, [1.0, 1.0], [1.0, 1.0], [2, 2])
    env.step(push)                           # a delayed command from before the reset never acts
    assert env.actuators.act.abs().max() == 0


def test_knobs_are_drawn_per_environment_within_their_ranges_and_repeat_with_the_seed():
    a, b = _env(64), _env(64)
    for name in ("gain", "alpha", "delay"):
        assert torch.equal(getattr(a.actuators, name), getattr(b.actuators, name))
    assert 0.5 <= float(a.actuators.gain.min()) and float(a.actuators.gain.max()) <= 1.5
    assert float(a.actuators.gain.std()) > 0.1
    alpha_lo = -math.expm1(-SC.dynamics.dt / 0.2)
    assert float(a.actuators.alpha.min()) >= alpha_lo - 1e-12 and float(a.actuators.alpha.max()) <= 1.0
    assert set(a.actuators.delay.tolist()) == {0, 1, 2, 3}


def test_a_perfect_distribution_builds_no_actuator_and_changes_nothing():
    """ScenarioDistribution() varies nothing: the same seed and actions give the same world."""
    plain = BatchedFormationEnv(SC, 4, seed=3)
    none = BatchedFormationEnv(SC, 4, seed=3, distribution=ScenarioDistribution())
    assert none.actuators is None
    obs_a, _ = plain.reset()
    obs_b, _ = none.reset()
    gen = torch.Generator().manual_seed(0)
    for _ in range(140):                                   # across an episode's end
        act = torch.rand(4, 3, 2, generator=gen) * 2 - 1
        ra, rb = plain.step(act), none.step(act)
        assert torch.equal(ra.obs, rb.obs) and torch.equal(ra.reward, rb.reward)
