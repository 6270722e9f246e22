"""The compiled compensator tick equals its numpy formulation bit for bit, on any sequence."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.mec import MecConfig, ModelErrorCompensator
from sim.scenario import Dynamics
from tests.controllers.mec_reference import NumpyMec

DYN = Dynamics()


def _script(seed: int, ticks: int) -> list[tuple[tuple[str, ...], np.ndarray, np.ndarray]]:
    """Ticks of (ids, measured velocities, a_safe): robots join, leave and reorder, rows go
    missing (NaN), commands turn non-finite, speeds exceed the limit, noise of 0-4 cm/s."""
    rng = np.random.default_rng(seed)
    pool = [f"r{k}" for k in range(7)]
    ids = tuple(pool[:3])
    vel = {rid: rng.normal(0.0, 0.1, 2) for rid in pool}
    noise = rng.choice([0.0, 0.005, 0.02, 0.04])
    script = []
    for _ in range(ticks):
        if rng.random() < 0.08:                          # someone joins, leaves or rows reorder
            choice = rng.integers(3)
            if choice == 0 and len(ids) < len(pool):
                ids = (*ids, next(r for r in pool if r not in ids))
            elif choice == 1 and len(ids) > 1:
                gone = ids[rng.integers(len(ids))]
                ids = tuple(r for r in ids if r != gone)
            else:
                ids = tuple(str(r) for r in rng.permutation(ids))
        a_safe = rng.uniform(-1.2, 1.2, (len(ids), 2))
        if rng.random() < 0.05:
            a_safe[rng.integers(len(ids)), rng.integers(2)] = rng.choice([np.nan, np.inf])
        measured = np.array([vel[r] for r in ids]) + rng.normal(0.0, noise + 1e-12, (len(ids), 2))
        if rng.random() < 0.1:
            measured[rng.integers(len(ids))] = np.nan
        if rng.random() < 0.05:
            measured *= 4.0                              # beyond the speed limit
        script.append((ids, measured, a_safe))
        for k, rid in enumerate(ids):                    # a plant with a gain error and a disturbance
            vel[rid] = vel[rid] + DYN.dt * (0.7 * np.where(np.isfinite(a_safe[k]), a_safe[k], 0.0) + 0.1 - DYN.damping * vel[rid])
    return script


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), delay=st.integers(0, 3), adapt=st.booleans(),
       max_disturbance=st.sampled_from([None, 0.3]))
def test_compiled_tick_equals_numpy_formulation(seed, delay, adapt, max_disturbance):
    config = MecConfig(max_delay_ticks=delay, adapt_noise=adapt, max_disturbance=max_disturbance)
    compiled, reference = ModelErrorCompensator(DYN, config), NumpyMec(DYN, config)
    for ids, measured, a_safe in _script(seed, 60):
        v_c, v_r = compiled.update(measured.copy(), ids), reference.update(measured.copy(), ids)
        np.testing.assert_array_equal(v_c, v_r)
        out_c, out_r = compiled.compensate(a_safe), reference.compensate(a_safe)
        for name in ("a_cmd", "d_hat", "gated", "compensation", "delay_ticks"):
            np.testing.assert_array_equal(getattr(out_c, name), getattr(out_r, name), err_msg=name)
        assert out_c.status is out_r.status
        for name in ("v_hat", "d_hat", "score", "sent", "charge", "level", "noise_var", "noise_count",
                     "y_prev", "r_prev"):
            np.testing.assert_array_equal(getattr(compiled, name), getattr(reference, name), err_msg=name)


def test_the_reference_is_not_the_compiled_code():
    """The parity test compares two implementations: the reference's tick is numpy's own."""
    assert NumpyMec._observe is not ModelErrorCompensator._observe
    assert NumpyMec._compensate is not ModelErrorCompensator._compensate
