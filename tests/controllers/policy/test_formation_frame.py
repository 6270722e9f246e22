"""The formation frame: the quarter turn that brings a formation into the right-to-left frame,
and networks that act the same on a scene turned by a quarter turn about the arena's centre."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.policy import (
    ActorConfig,
    CriticConfig,
    PolicyConfigError,
    build_actor,
    build_critic,
)
from controllers.policy.layers import formation_turn
from sim.distribution import turn_points
from sim.observations import fleet_tokens_np
from sim.scenario import make_scenario

SC = make_scenario("paper-4")
CENTRE = np.array([0.5, 0.5])


def _rotation(k: int) -> np.ndarray:
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][k]
    return np.array([[c, -s], [s, c]], dtype=float)


def _tokens(pos, vel, targets, polygon) -> torch.Tensor:
    return torch.from_numpy(fleet_tokens_np(pos, vel, targets, polygon, SC.arena).astype(np.float32))


@pytest.mark.parametrize(("targets_side", "turn"), [((-1, 0), 0), ((0, 1), 1), ((1, 0), 2), ((0, -1), 3)])
def test_the_turn_brings_the_targets_left_of_the_object(targets_side, turn):
    """Targets 0.2 m left of, above, right of or below the object: k = 0, 1, 2, 3 quarter turns
    counter-clockwise, the R_k that points m (targets' centroid from the object's) along -x."""
    side = np.array(targets_side, dtype=float)
    targets = CENTRE + 0.2 * side + np.array([[0.0, 0.1], [0.0, -0.1]]) @ _rotation(1 if side[0] == 0 else 0).T
    pos = CENTRE - 0.2 * side + np.array([[0.01, 0.02], [-0.02, 0.01]])
    tokens = _tokens(pos, np.zeros((2, 2)), targets, SC.polygon)
    got = formation_turn(tokens, None).numpy()
    want = _rotation(turn)
    assert np.array_equal(got, np.broadcast_to(want, got.shape))
    m = targets.mean(0) - CENTRE
    assert (want @ m)[0] == pytest.approx(-0.2) and abs((want @ m)[1]) < 1e-12


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(1, 3))
def test_a_turned_scene_gets_turned_actions_and_the_same_values(seed, k):
    """Positions, velocities, targets and the object turned by k quarter turns about the arena's
    centre: the actor's actions turn alike and the critic's values stay, to float32 rounding of
    the tokens. Without the frame they do not (the assertion has teeth: see the last lines)."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0.1, 0.9, (4, 2))
    vel = rng.uniform(-0.3, 0.3, (4, 2))
    rot = _rotation(k)
    turned = [np.asarray(turn_points(x, 90 * k, CENTRE)) for x in (pos, SC.targets, SC.polygon)]
    obs = _tokens(pos, vel, SC.targets, SC.polygon).unsqueeze(0)
    obs_turned = _tokens(turned[0], vel @ rot.T, turned[1], turned[2]).unsqueeze(0)
    torch.manual_seed(seed % 1000)
    actor, critic = build_actor(ActorConfig(), 4).eval(), build_critic(CriticConfig(), 4).eval()
    world = build_actor(ActorConfig(frame="world"), 4).eval()
    world.load_state_dict(actor.state_dict())
    with torch.no_grad():
        a, a_turned = actor(obs)[0].numpy(), actor(obs_turned)[0].numpy()
        v, v_turned = critic(obs), critic(obs_turned)
        w, w_turned = world(obs)[0].numpy(), world(obs_turned)[0].numpy()
    np.testing.assert_allclose(a_turned, a @ rot.T, atol=1e-5)
    torch.testing.assert_close(v_turned, v, atol=1e-5, rtol=0)
    assert np.abs(a).max() > 1e-3
    assert np.abs(w_turned - w @ rot.T).max() > 1e-4      # the world frame is not equivariant


def test_the_frame_defaults_by_variant_and_is_refused_where_it_cannot_apply():
    assert ActorConfig().frame == "formation" and ActorConfig(variant="slot").frame == "world"
    assert CriticConfig().frame == "formation" and CriticConfig(variant="mlp").frame == "world"
    with pytest.raises(PolicyConfigError, match="actor.frame 'formation' applies to the 'typed' variant"):
        ActorConfig(variant="mlp", frame="formation")
    with pytest.raises(PolicyConfigError, match="critic.frame must be one of"):
        CriticConfig(frame="robot")


def test_checkpoints_from_before_the_frame_keep_the_world_frame(tmp_path):
    from controllers.mappo.checkpoint import checkpoint_config

    config = {"actor": ActorConfig().to_dict(), "critic": CriticConfig().to_dict()}
    for net in config.values():
        del net["frame"]
    loaded = checkpoint_config({"config": config})
    assert loaded.actor.frame == "world" and loaded.critic.frame == "world"


@pytest.mark.parametrize("diagonal", [(-1, -1), (-1, 1), (1, 1), (1, -1)])
def test_every_robot_of_a_team_on_a_diagonal_layout_takes_the_same_turn(diagonal):
    """Targets' centroid on a diagonal from the object's: two turn scores tie in exact arithmetic,
    and each robot's m, summed from its own float32 tokens, differs in its last bits. A plain
    argmax let rounding choose per robot (68 of 200 teams split; the exported files chose
    otherwise again, 0.5 m/s^2 apart); the first score within TURN_TIE wins now."""
    rng = np.random.default_rng(0)
    offsets = np.array([[-0.05, 0.05], [0.0, 0.0], [0.05, -0.05]]) @ _rotation(1 if diagonal[0] == diagonal[1] else 0).T
    targets = CENTRE + 0.3 * np.array(diagonal, dtype=float) + offsets
    for _ in range(50):
        pos = rng.uniform(0.05, 0.95, (3, 2))
        turns = formation_turn(_tokens(pos, rng.uniform(-0.3, 0.3, (3, 2)), targets, SC.polygon), None).numpy()
        assert all(np.array_equal(t, turns[0]) for t in turns), turns
