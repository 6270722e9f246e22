import dataclasses

import numpy as np
import pytest

from sim.scenario import (
    MAX_ROBOTS,
    PRESETS,
    Dynamics,
    Scenario,
    ScenarioError,
    make_scenario,
    rectangle,
    transport_scenario,
)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_are_valid(name):
    sc = make_scenario(name)
    assert sc.starts.shape == sc.targets.shape == (sc.num_robots, 2)
    # starts are right of the object, targets left of it: the formation change crosses it
    assert sc.starts[:, 0].min() > sc.polygon[:, 0].max()
    assert sc.targets[:, 0].max() < sc.polygon[:, 0].min()


def test_paper_presets_match_the_paper():
    for n in (3, 4, 5):
        sc = make_scenario(f"paper-{n}")
        assert sc.num_robots == n
        assert sc.robot_radius * 2 == pytest.approx(0.08)
        assert sc.target_tolerance == pytest.approx(0.05)
        assert sc.arena == (1.0, 1.0)
        assert sc.dynamics.dt == pytest.approx(0.05) and sc.dynamics.episode_steps == 128


@pytest.mark.parametrize("n", range(1, MAX_ROBOTS + 1))
def test_any_robot_count_from_1_to_max(n):
    sc = transport_scenario(n)
    assert sc.num_robots == n


@pytest.mark.parametrize("name", ["transport-0", f"transport-{MAX_ROBOTS + 1}"])
def test_a_transport_name_out_of_range_names_the_scenario_and_the_range(name):
    with pytest.raises(ScenarioError, match=rf"scenario '{name}': transport-N takes N = 1\.\.{MAX_ROBOTS} robots"):
        make_scenario(name)
    assert make_scenario(f"transport-{MAX_ROBOTS}").num_robots == MAX_ROBOTS


def _base(**kw):
    sc = make_scenario("paper-3")
    fields = {f.name: getattr(sc, f.name) for f in dataclasses.fields(sc)}
    fields.update(kw)
    return fields


def test_overlapping_slots_name_the_field():
    starts = ((0.7, 0.40), (0.7, 0.45), (0.7, 0.65))
    with pytest.raises(ScenarioError, match=r"start_slots\[0\] and start_slots\[1\] overlap"):
        Scenario(**_base(start_slots=starts))


def test_slot_inside_object_names_the_field():
    targets = ((0.5, 0.5), (0.3, 0.3), (0.3, 0.7))
    with pytest.raises(ScenarioError, match=r"target_slots\[0\].*inside or touching the object"):
        Scenario(**_base(target_slots=targets))


def test_slot_outside_arena_names_the_field():
    targets = ((0.3, 0.3), (0.3, 0.5), (1.2, 0.7))
    with pytest.raises(ScenarioError, match=r"target_slots\[2\].*outside the arena"):
        Scenario(**_base(target_slots=targets))


def test_slot_count_mismatch():
    with pytest.raises(ScenarioError, match="start_slots has 2 slots but num_robots is 3"):
        Scenario(**_base(start_slots=((0.7, 0.3), (0.7, 0.6))))


def test_clockwise_polygon_rejected():
    cw = tuple(reversed(rectangle((0.5, 0.5), (0.2, 0.3))))
    with pytest.raises(ScenarioError, match="counter-clockwise"):
        Scenario(**_base(object_vertices=cw))


def test_bad_dynamics_named():
    with pytest.raises(ScenarioError, match="dynamics.speed_limit"):
        Scenario(**_base(dynamics=Dynamics(speed_limit=-1)))
    with pytest.raises(ScenarioError, match="dynamics.damping"):
        Scenario(**_base(dynamics=Dynamics(damping=30.0)))


def test_unknown_fields_are_errors():
    data = make_scenario("paper-3").to_dict()
    data["robots"] = 3
    with pytest.raises(ScenarioError, match=r"unknown scenario field\(s\) \['robots'\]"):
        Scenario.from_dict(data)
    data = make_scenario("paper-3").to_dict()
    data["dynamics"]["gravity"] = 9.8
    with pytest.raises(ScenarioError, match="unknown dynamics field"):
        Scenario.from_dict(data)


def test_round_trip_through_dict():
    sc = make_scenario("paper-5")
    again = Scenario.from_dict(sc.to_dict())
    assert again == sc


def test_polygon_object_allowed():
    tri = ((0.45, 0.35), (0.6, 0.5), (0.45, 0.65))
    sc = transport_scenario(3, object_vertices=tri)
    assert np.allclose(sc.object_center, [0.5, 0.5])


def test_unknown_preset():
    with pytest.raises(ScenarioError, match="unknown scenario 'paper-9'"):
        make_scenario("paper-9")


def test_numpy_step_matches_the_batched_world():
    import torch

    from sim.batched_env import BatchedFormationEnv
    from sim.scenario import clip_norm

    sc = make_scenario("paper-3")
    env = BatchedFormationEnv(sc, 1, seed=0, dtype=torch.float64)
    env.reset()
    pos = np.array([[0.2, 0.15], [0.5, 0.15], [0.8, 0.15]])
    vel = np.array([[0.39, 0.1], [0.0, 0.0], [-0.1, 0.05]])
    acc = np.array([[3.0, 4.0], [0.2, -0.1], [0.0, 1.0]])
    env.set_state(torch.tensor(pos)[None], torch.tensor(vel)[None])
    env.step(torch.tensor(acc)[None])
    p1, v1 = sc.dynamics.step_np(pos, vel, acc)
    assert np.allclose(p1, env.pos[0].numpy()) and np.allclose(v1, env.vel[0].numpy())
    assert np.allclose(clip_norm(np.array([[3.0, 4.0], [0.3, 0.4]]), 1.0), [[0.6, 0.8], [0.3, 0.4]])


def test_a_scenario_file_round_trips_what_scenarios_show_prints(tmp_path):
    import json

    from sim.scenario import Scenario

    preset = make_scenario("paper-4")
    path = tmp_path / "layout.json"
    path.write_text(json.dumps(preset.to_dict(), indent=2))
    assert make_scenario(str(path)) == preset
    toml = tmp_path / "layout.toml"
    d = preset.to_dict() | {"name": "from-toml"}
    lines = [f"{k} = {json.dumps(v)}" for k, v in d.items() if not isinstance(v, dict)]
    lines += ["[dynamics]"] + [f"{k} = {json.dumps(v)}" for k, v in d["dynamics"].items()]
    toml.write_text("\n".join(lines) + "\n")
    from_toml = make_scenario(str(toml))
    assert from_toml == Scenario.from_dict(d | {"name": "from-toml"})


@pytest.mark.parametrize("content, message", [
    ('{"name": "x"}', "missing"),
    ('{"name": "x", "colour": 1}', "colour"),
    ("[1, 2]", "mapping"),
    ("{not json", "not valid JSON"),
])
def test_a_bad_scenario_file_names_the_file_and_field(tmp_path, content, message):
    path = tmp_path / "bad.json"
    path.write_text(content)
    with pytest.raises(ScenarioError) as err:
        make_scenario(str(path))
    assert message in str(err.value) and "bad.json" in str(err.value)


def test_a_name_longer_than_a_file_name_is_an_unknown_scenario_not_an_os_error():
    with pytest.raises(ScenarioError, match="unknown scenario"):
        make_scenario("paper" * 60)


@pytest.mark.parametrize("change, message", [
    ({"arena": [1.0]}, "arena must be a (width, height) pair"),
    ({"arena": "11"}, "arena must be a (width, height) pair"),
    ({"robot_radius": "0.04"}, "robot_radius must be a number"),
    ({"target_tolerance": None}, "target_tolerance must be a number"),
    ({"start_jitter": True}, "start_jitter must be a number"),
    ({"num_robots": True}, "num_robots must be an integer"),
    ({"num_robots": 3.5}, "num_robots must be an integer"),
    ({"dynamics": {"dt": "0.05"}}, "dynamics.dt must be a number"),
    ({"dynamics": {"episode_steps": float("inf")}}, "dynamics.episode_steps must be an integer"),
    ({"dynamics": {"episode_steps": float("nan")}}, "dynamics.episode_steps must be an integer"),
    ({"dynamics": {"episode_steps": 12.5}}, "dynamics.episode_steps must be an integer"),
    ({"dynamics": [1, 2]}, "dynamics must be a mapping"),
])
def test_a_field_of_the_wrong_type_is_named_not_a_traceback(change, message):
    """Before: the arena was unpacked unchecked (a traceback), int(inf) overflowed, and
    float('x') errors named no field."""
    data = make_scenario("paper-3").to_dict() | change
    with pytest.raises(ScenarioError) as err:
        Scenario.from_dict(data)
    assert message in str(err.value)


def test_an_integral_episode_length_is_kept_as_an_integer():
    """128.0 (a TOML or JSON float) was kept as a float, which training could not range over."""
    data = make_scenario("paper-3").to_dict()
    data["dynamics"]["episode_steps"] = 128.0
    steps = Scenario.from_dict(data).dynamics.episode_steps
    assert steps == 128 and type(steps) is int


def test_a_start_slot_clears_the_object_by_the_diagonal_jitter():
    """The jitter is per axis, so a start may move sqrt(2) j: a slot diagonal to a corner
    needs r + sqrt(2) j. Before, r + j was enough, and 3.6 % of such starts overlapped the box."""
    import math

    data = make_scenario("paper-3").to_dict()
    r, j = data["robot_radius"], data["start_jitter"]
    corner = np.array([0.6, 0.65])                       # upper-right corner of the default box
    for clearance, ok in ((r + j + 1e-4, False), (r + math.sqrt(2) * j + 1e-4, True)):
        slot = corner + clearance / math.sqrt(2)
        data["start_slots"] = [slot.tolist(), [0.67, 0.45], [0.67, 0.3]]
        if ok:
            Scenario.from_dict(data)
        else:
            with pytest.raises(ScenarioError, match=r"start_slots\[0\].*sqrt\(2\) x start jitter"):
                Scenario.from_dict(data)


def test_a_repeated_vertex_is_named():
    """A ring-closed polygon (first vertex repeated last) passed validation, then made the
    safety filter's ear clipping raise on its first tick and its closed forms return NaN."""
    data = make_scenario("paper-3").to_dict()
    data["object_vertices"] = [*data["object_vertices"], data["object_vertices"][0]]
    with pytest.raises(ScenarioError, match=r"object_vertices\[4\] and object_vertices\[0\] are the same"):
        Scenario.from_dict(data)


def test_another_team_size_keeps_the_arena_radius_and_tolerance():
    """with_robots (every team size of a team_sizes run) fell back to the defaults."""
    base = make_scenario("paper-3")
    small = Scenario.from_dict(base.to_dict() | {"robot_radius": 0.035, "target_tolerance": 0.02})
    four = small.with_robots(4)
    assert (four.robot_radius, four.target_tolerance, four.arena, four.num_robots) == (0.035, 0.02, (1.0, 1.0), 4)
    big = transport_scenario(3, object_vertices=rectangle((1.0, 1.0), (0.2, 0.3)), arena=(2.0, 2.0))
    assert big.with_robots(5).arena == (2.0, 2.0)
