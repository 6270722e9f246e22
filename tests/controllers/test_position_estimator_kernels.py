"""The compiled position estimator equals its numpy formulation bit for bit, on any sequence."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.position_estimator import PositionEstimator
from tests.controllers.position_estimator_reference import NumpyPositionEstimator

DT = 0.05


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), noise=st.sampled_from([0.0, 5e-5, 0.01]))
def test_compiled_tick_equals_numpy_formulation(seed, noise):
    """Robots join, leave and reorder; measurements repeat (not new), skip ticks, go non-finite,
    jump (a contact: out of model); noise below, at and above the floor."""
    rng = np.random.default_rng(seed)
    compiled, reference = PositionEstimator(DT), NumpyPositionEstimator(DT)
    pool = [f"r{k}" for k in range(6)]
    truth = {rid: rng.uniform(0.1, 0.9, 2) for rid in pool}
    ids, t = tuple(pool[:3]), 0.0
    for _ in range(60):
        if rng.random() < 0.1:
            ids = tuple(str(r) for r in rng.permutation(pool)[: rng.integers(1, len(pool) + 1)])
        n = len(ids)
        t += DT * rng.choice([1, 1, 1, 2])
        vel = rng.normal(0.0, 0.1, (n, 2))
        for k, rid in enumerate(ids):
            truth[rid] = truth[rid] + DT * vel[k] + (0.2 if rng.random() < 0.03 else 0.0)
        pos = np.array([truth[r] for r in ids]) + rng.normal(0.0, noise + 1e-300, (n, 2))
        times = np.full(n, t) - DT * (rng.random(n) < 0.1)
        new = rng.random(n) < 0.9
        if rng.random() < 0.1:
            pos[rng.integers(n)] = np.nan
        noise_var = rng.uniform(0.0, 4e-4, n)
        outs = [est.update(ids, pos, vel, times, new, noise_var) for est in (compiled, reference)]
        for a, b in zip(outs[0], outs[1], strict=True):
            np.testing.assert_array_equal(a, b)
        for name in ("p_hat", "var", "y_prev", "t_prev", "noise_var", "passed", "count"):
            np.testing.assert_array_equal(getattr(compiled, name), getattr(reference, name), err_msg=name)


def test_rows_of_the_wrong_length_are_refused_with_the_field_named():
    est = PositionEstimator(DT)
    with pytest.raises(ValueError, match=r"vel must have shape \(2, 2\)"):
        est.update(("a", "b"), np.zeros((2, 2)), np.zeros((3, 2)), np.zeros(2), np.ones(2, bool), np.zeros(2))
    with pytest.raises(ValueError, match=r"velocity_noise_var must have shape \(2,\)"):
        est.update(("a", "b"), np.zeros((2, 2)), np.zeros((2, 2)), np.zeros(2), np.ones(2, bool), np.zeros(1))


def test_the_reference_is_not_the_compiled_code():
    assert NumpyPositionEstimator._estimate is not PositionEstimator._estimate
