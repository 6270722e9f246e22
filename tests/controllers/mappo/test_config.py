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
