"""ModelError: its fields are validated with errors that name them; the defaults are a perfect robot."""

import pytest

from sim.model_error import ModelError


@pytest.mark.parametrize("field, value", [
    ("gain", 0.0), ("gain", float("nan")), ("gain_spread", -0.1), ("gain_spread", 1.0),
    ("lag_tau", -0.01), ("delay_ticks", -1), ("delay_ticks", 1.5), ("delay_ticks", True),
    ("disturbance", (0.1,)), ("disturbance", (0.0, float("inf"))), ("disturbance", 3.0),
    ("disturbance_std", -1.0), ("floor_friction", -0.2), ("position_noise_std", -1e-3),
    ("velocity_noise_std", float("inf")), ("gain", "1"),
])
def test_bad_model_error_fields_raise_naming_the_field(field, value):
    with pytest.raises(ValueError, match=rf"ModelError\.{field}\b"):
        ModelError(**{field: value})


def test_model_error_defaults_are_a_perfect_robot():
    me = ModelError()
    assert (me.gain, me.gain_spread, me.lag_tau, me.delay_ticks, me.disturbance) == (1.0, 0.0, 0.0, 0, (0.0, 0.0))
    assert me.disturbance_std == me.floor_friction == me.position_noise_std == me.velocity_noise_std == 0.0
