import pytest
import torch

from sim.metrics import collision_events
from sim.reward import RewardWeights, formation_reward
from sim.scenario import make_scenario

POLY = torch.as_tensor(make_scenario("paper-3").polygon)


def test_reward_by_hand():
    targets = torch.tensor([[[0.3, 0.4], [0.3, 0.6]]])
    # robot 0 on target 0 exactly, robot 1 0.3 to the right of target 1 (x = 0.6 is the box edge,
    # so put it at (0.3, 0.9): 0.3 above target 1, clear of everything)
    pos = torch.tensor([[[0.3, 0.4], [0.3, 0.9]]])
    ev = collision_events(pos, POLY, 0.04, (1.0, 1.0))
    r = formation_reward(pos, targets, ev, 0.05)
    # to_target: target 0 -> 0 (robot 0), target 1 -> 0.2 (robot 0 is nearer than robot 1's 0.3)
    # to_robot: robot 0 -> 0, robot 1 -> 0.3 (target 1)
    # cover = 0.5 * (0.1 + 0.15) = 0.125; arrived = 1/2; r = -0.125 + 0.1 * 0.5 = -0.075
    assert r[0].tolist() == pytest.approx([-0.075, -0.075])


def test_collision_penalties_are_per_robot():
    targets = torch.tensor([[[0.3, 0.4], [0.3, 0.6], [0.2, 0.2]]])
    pos = torch.tensor([[[0.3, 0.4], [0.3, 0.46], [0.02, 0.2]]])   # 0 and 1 touch; 2 in the wall
    ev = collision_events(pos, POLY, 0.04, (1.0, 1.0))
    w = RewardWeights()
    r = formation_reward(pos, targets, ev, 0.05, w)
    team = r[0, 0] + w.w_robot
    assert r[0, 1] == pytest.approx(team - w.w_robot)
    assert r[0, 2] == pytest.approx(team - w.w_wall)


def test_reward_is_maximal_when_every_target_is_held():
    targets = torch.tensor([[[0.3, 0.3], [0.3, 0.5], [0.3, 0.7]]])
    ev = collision_events(targets, POLY, 0.04, (1.0, 1.0))
    assert formation_reward(targets, targets, ev, 0.05)[0].tolist() == pytest.approx([0.1] * 3)


def test_min_over_matches_torch_min():
    from sim.reward import _min_over

    x = torch.rand(7, 5, 5, generator=torch.Generator().manual_seed(0))
    for dim in (-1, -2):
        assert torch.equal(_min_over(x, dim), x.min(dim).values)
    big = torch.rand(2, 12, 12)
    assert torch.equal(_min_over(big, -1), big.min(-1).values)


def test_onset_penalty_is_charged_once_per_new_contact():
    from sim.batched_env import BatchedFormationEnv
    from sim.scenario import make_scenario

    sc = make_scenario("paper-3")
    w = RewardWeights(w_onset=3.0)
    env = BatchedFormationEnv(sc, 1, seed=0, reward_weights=w, dtype=torch.float64)
    plain = BatchedFormationEnv(sc, 1, seed=0, dtype=torch.float64)
    for e in (env, plain):
        e.reset()
        # robots 0 and 1 are 0.07 m apart (< 0.08): a standing contact from the first step
        pos = torch.tensor([[[0.2, 0.2], [0.27, 0.2], [0.8, 0.15]]], dtype=torch.float64)
        e.set_state(pos, torch.zeros_like(pos))
    a = torch.zeros(1, 3, 2, dtype=torch.float64)
    first, first_plain = env.step(a).reward, plain.step(a).reward
    second, second_plain = env.step(a).reward, plain.step(a).reward
    # the contact starts in step 1: robots 0 and 1 pay 3.0 once, robot 2 never
    assert (first - first_plain)[0].tolist() == pytest.approx([-3.0, -3.0, 0.0])
    assert (second - second_plain)[0].tolist() == pytest.approx([0.0, 0.0, 0.0])


def _frame(pos):
    from sim.geometry import Frame, Polygon

    pos = torch.tensor([pos], dtype=torch.float64)
    return Frame(pos, torch.zeros_like(pos), pos.clone(), Polygon(POLY.to(torch.float64)))


def test_proximity_ramp_by_hand():
    from sim.reward import proximity_ramp

    # robots 0, 1: gap 0.09 - 0.08 = 0.01 -> ramp 1 - 0.01/0.02 = 0.5 each;
    # robot 2: 0.01 from the box's right face (x = 0.6 + 0.04 + 0.01) -> 0.5; robot 0: 0.005 from
    # the bottom wall (y = 0.045) -> 0.75; everything else farther than the 0.02 margin
    near = proximity_ramp(_frame([[0.2, 0.045], [0.29, 0.045], [0.65, 0.5]]), 0.04, (1.0, 1.0), 0.02)
    assert near[0].tolist() == pytest.approx([0.5 + 0.75, 0.5 + 0.75, 0.5])
    with pytest.raises(ValueError, match="near_margin"):
        proximity_ramp(_frame([[0.2, 0.2]]), 0.04, (1.0, 1.0), 0.0)


# two robots far apart and from the object: no contact term, only the distance terms differ
APART = torch.tensor([[[0.2, 0.2], [0.8, 0.2]]])


def _added(d: torch.Tensor, **weights) -> list[float]:
    """Per-robot reward that ``weights`` add to the default reward at distances ``d`` (1, 2, 2)."""
    from sim.reward import reward_from_distances

    ev = collision_events(APART, POLY, 0.04, (1.0, 1.0))
    return (reward_from_distances(d, ev, 0.05, RewardWeights(**weights))
            - reward_from_distances(d, ev, 0.05, RewardWeights()))[0].tolist()


def test_own_and_assigned_terms_by_hand():
    # straight distances, robot i -> target k: both robots nearest to target 0, so the nearest-
    # target term charges 0.1 and 0.2, but the best one-to-one assignment is 0->1, 1->0
    # (0.3 + 0.2 = 0.5 < 0.1 + 0.6), so the assignment term charges 0.3 and 0.2
    d = torch.tensor([[[0.1, 0.3], [0.2, 0.6]]])
    assert _added(d, w_own=2.0) == pytest.approx([-0.2, -0.4])
    assert _added(d, w_assigned=1.0) == pytest.approx([-0.3, -0.2])


def test_squared_assignment_sends_the_leader_of_a_queue_to_the_far_target():
    # two robots queue along one path past the near target (0) to the far one (1): the leader
    # is 0.1 m from target 0 and 0.225 m from target 1, the follower 0.3 m and 0.42 m. Linear sums
    # send the leader to the near target (0.1 + 0.42 = 0.52 < 0.225 + 0.3 = 0.525), where it
    # blocks the follower; squared sums send it to the far one (0.0506 + 0.09 < 0.01 + 0.1764).
    # The charged distances stay linear.
    d = torch.tensor([[[0.1, 0.225], [0.3, 0.42]]])
    assert _added(d, w_assigned=1.0) == pytest.approx([-0.1, -0.42])
    assert _added(d, w_assigned=1.0, assignment_power=2.0) == pytest.approx([-0.225, -0.3])


def test_penalty_scale_multiplies_only_the_contact_terms():
    from sim.reward import reward_from_distances

    d = torch.tensor([[[0.1, 0.3], [0.2, 0.6]]])
    pos = torch.tensor([[[0.2, 0.2], [0.23, 0.2]]])          # 3 cm apart: the robots overlap
    ev = collision_events(pos, POLY, 0.04, (1.0, 1.0))
    onsets = torch.tensor([[True, False]])
    w = RewardWeights(w_onset=2.0, w_assigned=1.0)
    plain = reward_from_distances(d, ev, 0.05, w, onsets=onsets)
    tripled = reward_from_distances(d, ev, 0.05, w, onsets=onsets, penalty_scale=3.0)
    # robot 0 pays w_robot + w_onset = 2.5, robot 1 pays w_robot = 0.5; tripled: 2x more of each
    assert (plain - tripled)[0].tolist() == pytest.approx([2 * 2.5, 2 * 0.5])


def test_own_arrival_bonus_goes_to_the_robot_on_its_assigned_target():
    # the assignment is 0->1, 1->0 (0.04 + 0.3 < 0.02 + 0.5): robot 0 is within tolerance of its
    # assigned target 1 (0.04 <= 0.05) and earns the bonus; robot 1 (0.3 from target 0) does not
    d = torch.tensor([[[0.02, 0.04], [0.3, 0.5]]])
    assert _added(d, w_own_arrive=0.7) == pytest.approx([0.7, 0.0])
    assert _added(d + 0.05, w_own_arrive=0.7) == [0.0, 0.0]


def test_contact_margin_moves_the_penalty_not_the_statistics():
    from sim.batched_env import BatchedFormationEnv

    sc = make_scenario("paper-3")
    # robot 0 rests 5 mm from the box's right face: no contact, but inside a 1 cm margin
    pos = torch.tensor([[[0.645, 0.5], [0.2, 0.15], [0.8, 0.15]]], dtype=torch.float64)
    rewards = {}
    for margin in (0.0, 0.01):
        env = BatchedFormationEnv(sc, 1, seed=0, dtype=torch.float64,
                                  reward_weights=RewardWeights(contact_margin=margin, w_onset=3.0))
        env.reset()
        env.set_state(pos, torch.zeros_like(pos))
        rewards[margin] = [env.step(torch.zeros(1, 3, 2, dtype=torch.float64)).reward for _ in range(2)]
        assert env.counts[0].tolist() == [0, 0, 0] and not env.collided[0]
    w = RewardWeights()
    first = (rewards[0.0][0] - rewards[0.01][0])[0].tolist()
    second = (rewards[0.0][1] - rewards[0.01][1])[0].tolist()
    assert first == pytest.approx([w.w_object + 3.0, 0.0, 0.0])     # per-step penalty + one onset
    assert second == pytest.approx([w.w_object, 0.0, 0.0])
