"""Scenario distributions: every draw is a valid layout of the kind asked for; the training
world draws a fresh layout when all its environments restart; errors name the field."""

import json

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st

from sim.batched_env import BatchedFormationEnv
from sim.distribution import (
    DIRECTIONS,
    DISTRIBUTIONS,
    DistributionError,
    ScenarioDistribution,
    load_distribution,
    object_polygon,
)
from sim.scenario import make_scenario, polygon_signed_area

BASE = make_scenario("paper-3")
BROAD = DISTRIBUTIONS["broad"]


def _signed_area(vertices) -> float:
    return polygon_signed_area(np.asarray(vertices))


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 8), seed=st.integers(0, 2**32 - 1))
@example(n=1, seed=7069)     # a 6 cm thin polygon crossed top to bottom: the move is 0.198 m
def test_every_broad_draw_is_a_valid_layout_whose_robots_move_the_named_way(n, seed):
    """Scenario() validates each draw (slots in the arena, off the object, apart); the direction
    in its name is where the targets lie from the starts, across the object's centre: the team
    moves at least the object's extent along that axis plus a robot diameter."""
    sc = BROAD.layout(BASE, n, np.random.default_rng(seed))
    direction = sc.name.split("-")[0]
    move = sc.targets.mean(0) - sc.starts.mean(0)
    axis, sign = {"right_to_left": (0, -1), "left_to_right": (0, 1), "top_to_bottom": (1, -1),
                  "bottom_to_top": (1, 1)}[direction]
    w, h = np.ptp(sc.polygon, 0)
    assert sign * move[axis] > (w, h)[axis] + 2 * sc.robot_radius and abs(move[1 - axis]) < 1e-9
    c = sc.object_center
    assert sign * (c[axis] - sc.starts[:, axis]).min() > 0 and sign * (sc.targets[:, axis] - c[axis]).min() > 0
    assert w <= 0.4 + 1e-6 and h <= 0.4 + 1e-6
    if "-box-" in sc.name:                  # a polygon's vertices need not reach its box
        assert 0.1 - 1e-6 <= w and 0.1 - 1e-6 <= h
        assert np.abs(c - 0.5).max() <= 0.05 + 1e-6      # the offset bound
    assert 0.0 <= sc.start_jitter <= 0.02 and sc.dynamics == BASE.dynamics


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), w=st.floats(0.05, 0.5), h=st.floats(0.05, 0.5))
def test_polygons_are_convex_counter_clockwise_and_fill_their_box(seed, w, h):
    rng = np.random.default_rng(seed)
    poly = np.asarray(object_polygon("polygon", np.array([0.5, 0.5]), (w, h), rng))
    assert 5 <= len(poly) <= 8 and _signed_area(poly) > 0
    edges = np.roll(poly, -1, 0) - poly
    turns = edges[:, 0] * np.roll(edges[:, 1], -1) - edges[:, 1] * np.roll(edges[:, 0], -1)
    assert (turns > 0).all()                                     # convex: every turn to the left
    x, y = (poly - 0.5).T
    assert np.allclose((x / (w / 2)) ** 2 + (y / (h / 2)) ** 2, 1.0, atol=1e-4)   # on the ellipse


def test_all_four_directions_and_both_shapes_are_drawn():
    rng = np.random.default_rng(0)
    names = {BROAD.layout(BASE, 4, rng).name.rsplit("-", 1)[0] for _ in range(200)}
    assert names == {f"{d}-{s}" for d in DIRECTIONS for s in ("box", "polygon")}


def test_the_default_distribution_is_the_preset_layout():
    d = ScenarioDistribution()
    assert not d.varies_layout and not d.varies_dynamics
    sc = d.layout(BASE, 3, np.random.default_rng(0))
    assert np.array_equal(sc.starts, BASE.starts) and np.array_equal(sc.targets, BASE.targets)
    assert np.allclose(sc.polygon, BASE.polygon)


def test_the_training_world_draws_a_new_layout_when_all_its_environments_restart():
    env = BatchedFormationEnv(BASE, 4, seed=0, distribution=BROAD)
    env.reset()
    first = env.scenario
    assert torch.allclose(env.targets[0], torch.as_tensor(first.targets, dtype=torch.float32))
    env.reset(env_ids=torch.tensor([1]))                 # one alone: the layout stays
    assert env.scenario is first
    layouts = [first.name]
    for _ in range(3 * BASE.dynamics.episode_steps):
        out = env.step(torch.zeros(4, 3, 2))
        if out.done.any():
            assert out.done.sum() >= 3                   # env 1 restarted later, alone
            layouts.append(env.scenario.name)
    assert env.scenario is not first
    dist = (env.pos - env.start_slots).abs().max()
    assert float(dist) < 0.5                             # robots stand near the new layout's starts
    again = BatchedFormationEnv(BASE, 4, seed=0, distribution=BROAD)
    again.reset()
    assert again.scenario == first                       # the seed repeats the draws


@settings(max_examples=30, deadline=None)
@given(n=st.integers(2, 7), seed=st.integers(0, 2**32 - 1))
def test_slot_spacing_draws_columns_of_that_spacing(n, seed):
    """Neighbouring targets (and starts) of a draw lie one drawn spacing apart, in the range;
    the draw is a valid layout (Scenario() checks slots against walls and the object)."""
    d = ScenarioDistribution(slot_spacing=(0.09, 0.15))
    assert d.varies_layout
    sc = d.layout(BASE, n, np.random.default_rng(seed))
    for slots in (sc.targets, sc.starts):
        gaps = np.diff(np.sort(slots[:, 1]))
        assert np.allclose(gaps, gaps[0], atol=1e-9) and 0.09 - 1e-9 <= gaps[0] <= 0.15 + 1e-9
    # closer start slots could touch after jitter: such draws are drawn again (0.122 m here)
    start_gap = np.diff(np.sort(sc.starts[:, 1]))[0]
    assert start_gap >= 2 * sc.robot_radius + 2 * np.sqrt(2) * sc.start_jitter - 1e-9


def test_slot_spacing_varies_between_draws_and_refuses_overlapping_robots():
    d = ScenarioDistribution(slot_spacing=(0.09, 0.15))
    rng = np.random.default_rng(0)
    spacings = {round(float(np.diff(d.layout(BASE, 3, rng).targets[:, 1])[0]), 4) for _ in range(20)}
    assert len(spacings) > 10
    with pytest.raises(DistributionError, match=r"slot_spacing must satisfy 0.09 <= low"):
        ScenarioDistribution(slot_spacing=(0.05, 0.1))


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 6), seed=st.integers(0, 2**32 - 1), direction=st.sampled_from(sorted(DIRECTIONS)))
def test_slot_pool_draws_starts_and_targets_among_the_slots_of_a_larger_layout(n, seed, direction):
    """With slot_pool [lo, hi] a team of n robots takes n distinct start slots and n distinct
    target slots of the K-robot layout, K in max(n, lo)..max(n, hi): every slot of the draw is one
    of transport-K's (turned the drawn way), for some K in the range."""
    from sim.distribution import turn_points
    from sim.scenario import transport_scenario

    d = ScenarioDistribution(slot_pool=(3, 10), directions=(direction,))
    sc = d.layout(BASE, n, np.random.default_rng(seed))
    centre = np.asarray(BASE.arena) / 2

    def slots_of(k):
        full = transport_scenario(k, object_vertices=turn_points(BASE.polygon, -DIRECTIONS[direction], centre))
        return (np.asarray(turn_points(full.starts, DIRECTIONS[direction], centre)),
                np.asarray(turn_points(full.targets, DIRECTIONS[direction], centre)))

    def within(points, slots):
        return all(np.abs(slots - p).max(1).min() < 1e-9 for p in points)

    fits = [k for k in range(max(n, 3), max(n, 10) + 1)
            if within(sc.starts, slots_of(k)[0]) and within(sc.targets, slots_of(k)[1])]
    assert fits, "the draw's slots are not those of any transport-K layout in the pool's range"
    for slots in (sc.starts, sc.targets):
        assert len({tuple(t) for t in np.round(slots, 9)}) == n      # without replacement


def test_slot_pool_reaches_the_outer_and_second_column_slots_and_is_refused_out_of_range():
    """Three robots drawn from a pool of up to ten reach target slots no 3-robot preset has: the
    second column (x 0.125 further out) and the column's ends near the walls; an empty pool (the
    default) is the preset itself; a pool past 21 robots or of non-integers is refused by name."""
    d = ScenarioDistribution(slot_pool=(3, 10))
    rng = np.random.default_rng(0)
    targets = np.concatenate([d.layout(BASE, 3, rng).targets for _ in range(200)])
    preset = BASE.targets
    assert targets[:, 0].min() == pytest.approx(preset[:, 0].min() - 0.125)       # a second column
    assert targets[:, 1].min() == pytest.approx(0.5 - 3 * 0.125)                   # 7 to a column
    default = ScenarioDistribution()
    assert not default.varies_layout and ScenarioDistribution(slot_pool=(3, 10)).varies_layout
    same = ScenarioDistribution(slot_pool=(0, 0), slot_spacing=(0.14, 0.14)).layout(BASE, 3, np.random.default_rng(1))
    assert np.diff(same.targets[:, 1]) == pytest.approx([0.14, 0.14])             # every slot used
    with pytest.raises(DistributionError, match=r"slot_pool must satisfy 0 <= low <= high <= 21"):
        ScenarioDistribution(slot_pool=(3, 22))
    with pytest.raises(DistributionError, match=r"slot_pool must be a pair of integers"):
        ScenarioDistribution(slot_pool=(3, 7.5))
    with pytest.raises(DistributionError, match=r"no layout of 3 robots .* slot_pool"):   # 3 columns beside 0.6 m
        ScenarioDistribution(slot_pool=(21, 21), object_width=(0.6, 0.6)).layout(BASE, 3, np.random.default_rng(0))


def test_a_single_value_other_than_the_presets_is_drawn_too():
    """object_width [0.3, 0.3] alone is a 0.3 m object in the training world, not the preset's
    0.2 (a varies_layout that looked for ranges only kept the preset); slot_spacing alike."""
    for d, check in ((ScenarioDistribution(object_width=(0.3, 0.3)),
                      lambda sc: np.ptp(sc.polygon[:, 0]) == pytest.approx(0.3)),
                     (ScenarioDistribution(slot_spacing=(0.14, 0.14)),
                      lambda sc: np.diff(np.sort(sc.targets[:, 1])) == pytest.approx([0.14, 0.14]))):
        assert d.varies_layout
        env = BatchedFormationEnv(BASE, 2, seed=0, distribution=d)
        env.reset()
        assert check(env.scenario)


def test_a_distribution_file_round_trips_and_bad_fields_are_named(tmp_path):
    path = tmp_path / "d.json"
    path.write_text(json.dumps(BROAD.to_dict()))
    assert load_distribution(str(path)) == BROAD
    assert load_distribution("broad") is BROAD
    toml = tmp_path / "d.toml"
    toml.write_text('directions = ["left_to_right"]\nobject_width = [0.1, 0.2]\n')
    assert load_distribution(str(toml)).directions == ("left_to_right",)
    for data, message in (({"object_width": [0.3, 0.1]}, "object_width must satisfy"),
                          ({"directions": ["sideways"]}, r"directions: unknown choice\(s\) \['sideways'\]"),
                          ({"directions": "left_to_right"}, "directions must be a non-empty list"),
                          ({"delay_ticks": [0, 1.5]}, "delay_ticks must be a pair of integers"),
                          ({"gain": [0.5, 1.0], "gain_spread": 0.6}, "gain_spread must be"),
                          ({"colour": "red"}, r"unknown distribution field\(s\) \['colour'\]")):
        with pytest.raises(DistributionError, match=message):
            ScenarioDistribution.from_dict(data)
    bad = tmp_path / "bad.json"
    bad.write_text('{"object_offset": [0.1]}')
    with pytest.raises(DistributionError, match="bad.json.*object_offset must be"):
        load_distribution(str(bad))
    with pytest.raises(DistributionError, match="broad"):
        load_distribution("no-such-distribution")


def test_a_distribution_that_cannot_place_the_team_says_which_fields_to_narrow():
    huge = ScenarioDistribution(object_width=(0.8, 0.9), object_height=(0.8, 0.9))
    with pytest.raises(DistributionError, match="narrow object_width"):
        huge.layout(BASE, 3, np.random.default_rng(0))


def test_inline_json_longer_than_a_file_name_is_read_and_long_junk_is_refused_by_name():
    text = json.dumps({**DISTRIBUTIONS["broad"].to_dict(), "slot_spacing": [0.12, 0.14]})
    assert len(text) > 255                                   # more than a file name may hold
    assert load_distribution(text).slot_spacing == (0.12, 0.14)
    with pytest.raises(DistributionError, match="neither a name"):
        load_distribution("b" * 300)


def test_layouts_are_drawn_in_the_base_scenarios_arena_with_its_robots():
    """The canonical layout was checked against the default 1 x 1 arena: a valid 2 x 2 scenario
    drew nothing at all."""
    from sim.scenario import Scenario

    d = make_scenario("paper-3").to_dict()
    shift = lambda pts: [[x + 0.5, y + 0.5] for x, y in pts]   # noqa: E731
    d.update(arena=[2.0, 2.0], start_slots=shift(d["start_slots"]), target_slots=shift(d["target_slots"]),
             object_vertices=shift(d["object_vertices"]), robot_radius=0.035, target_tolerance=0.03)
    drawn = ScenarioDistribution(object_width=(0.2, 0.21)).layout(Scenario.from_dict(d), 3, np.random.default_rng(0))
    assert drawn.arena == (2.0, 2.0) and (drawn.robot_radius, drawn.target_tolerance) == (0.035, 0.03)
    assert np.allclose(drawn.object_center, [1.0, 1.0], atol=1e-9)


def test_an_infinite_integer_range_is_named():
    with pytest.raises(DistributionError, match="delay_ticks must be a"):
        ScenarioDistribution(delay_ticks=(0, float("inf")))
