"""MAPPOConfig: a value of the wrong type is refused by name, never read as another."""

from __future__ import annotations

import math

import pytest

from controllers.mappo import MAPPOConfig, TrainConfigError
from controllers.policy.config import PolicyConfigError


@pytest.mark.parametrize(("fields", "message"), [
    ({"anneal_lr": "false"}, "anneal_lr must be true or false, got 'false'"),   # was read as on
    ({"value_norm": 1}, "value_norm must be true or false"),
    ({"stop_at_convergence": "no"}, "stop_at_convergence must be true or false"),
    ({"lr": True}, "lr must be a positive number, got True"),                   # was lr = 1.0
    ({"seed": True}, "seed must be an integer >= 0, got True"),
    ({"critic_lr": math.inf}, "critic_lr must be a positive number or null, got inf"),
    ({"value_clip": math.nan}, "value_clip must be a positive number or null"),
    ({"gamma": True}, r"gamma must be in \[0.0, 1.0\]"),
])
def test_a_wrongly_typed_setting_is_refused_by_name(fields, message):
    with pytest.raises(TrainConfigError, match=message):
        MAPPOConfig.from_dict({"scenario": "paper-3", **fields})


@pytest.mark.parametrize(("actor", "message"), [
    ({"init_log_std": None}, r"actor.init_log_std must be a number in \[-5, 2\], got None"),   # was a TypeError
    ({"init_log_std": "x"}, r"actor.init_log_std must be a number in \[-5, 2\], got 'x'"),
    ({"velocity_damping": True}, r"actor.velocity_damping must be a number in \[0, 100\] 1/s"),
    ({"input_scale": 0.0}, "actor.input_scale must be a number > 0"),
])
def test_a_wrongly_typed_actor_setting_is_refused_by_name(actor, message):
    with pytest.raises(PolicyConfigError, match=message):
        MAPPOConfig.from_dict({"scenario": "paper-3", "actor": actor})


def test_every_team_size_keeps_the_scenarios_robots_and_a_size_that_cannot_fit_is_named():
    """Other team sizes fell back to the default radius and tolerance (an easier task, counted
    in the run's worst-size success); a size whose layout leaves the arena raised uncaught."""
    from sim.scenario import make_scenario, rectangle, transport_scenario

    strict = make_scenario("paper-3").to_dict() | {"robot_radius": 0.035, "target_tolerance": 0.02}
    config = MAPPOConfig(scenario=strict, team_sizes=[3, 4, 5])
    assert {(s.num_robots, s.robot_radius, s.target_tolerance) for s in config.build_team_scenarios()} == {
        (3, 0.035, 0.02), (4, 0.035, 0.02), (5, 0.035, 0.02)}
    narrow = transport_scenario(3, object_vertices=rectangle((0.5, 0.5), (0.2, 0.3)), arena=(1.0, 0.7)).to_dict()
    with pytest.raises(TrainConfigError, match="team_sizes: the layout of a team size does not fit"):
        MAPPOConfig(scenario=narrow, team_sizes=[3, 5])
