"""The compiled latency prediction equals its numpy formulation bit for bit, on any sequence."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.safety.latency import LatencyConfig, LatencyPredictor, horizon_ticks
from sim.scenario import Dynamics, clip_norm
from tests.controllers.safety.latency_reference import NumpyPredictor

DYN = Dynamics()
FIELDS = ("pos", "vel", "grow", "closing", "fixed", "horizon", "brake_vel", "velocity_error", "unsure")


def _ticks(seed: int, count: int):
    """Per tick: ids, pos, vel, ages, a_nom, pending (or None), fixed (or None), position and
    velocity noise (or None), the measured delay, and the commands then recorded. Robots join,
    leave and reorder; ages run from fresh to stale; pending counts are unknown, equal for all
    (the fast path), mixed, or beyond the bound (late robots); speeds reach the limit."""
    rng = np.random.default_rng(seed)
    pool = [f"r{k}" for k in range(6)]
    ids = tuple(pool[:3])
    for _ in range(count):
        if rng.random() < 0.1:
            ids = tuple(str(r) for r in rng.permutation(pool)[: rng.integers(1, len(pool) + 1)])
        n = len(ids)
        pos = rng.uniform(0.0, 1.0, (n, 2))
        vel = rng.uniform(-0.5, 0.5, (n, 2))
        ages = rng.choice([0.0, 0.02, 0.04, 0.05, 0.1, 0.2, 0.4], n, p=[0.45, 0.1, 0.1, 0.15, 0.1, 0.05, 0.05])
        a_nom = clip_norm(rng.uniform(-1.5, 1.5, (n, 2)), DYN.accel_limit)
        kind = rng.integers(4)
        pending = (None if kind == 0 else np.full(n, rng.integers(0, 4)) if kind == 1
                   else rng.integers(-1, 6, n))
        fixed = rng.random(n) < 0.15 if rng.random() < 0.3 else None
        position_noise = rng.uniform(0.0, 0.01, n) if rng.random() < 0.5 else None
        velocity_noise = rng.uniform(0.0, 0.02, n) if rng.random() < 0.5 else None
        measured = rng.choice([None, 0.0, 0.1, 0.3])
        recorded = clip_norm(rng.uniform(-1.5, 1.5, (n, 2)), DYN.accel_limit)
        braking = rng.random(n) < 0.2
        yield ids, pos, vel, ages, a_nom, pending, fixed, position_noise, velocity_noise, measured, recorded, braking


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), delay=st.sampled_from([0.0, 0.05, 0.15]),
       noise=st.sampled_from([(0.0, 0.0), (0.01, 0.02)]), with_now=st.booleans())
def test_compiled_prediction_equals_numpy_formulation(seed, delay, noise, with_now):
    config = LatencyConfig(command_delay_s=delay, position_noise=noise[0], velocity_noise=noise[1])
    compiled, reference = LatencyPredictor(DYN, config), NumpyPredictor(DYN, config)
    for t, (ids, pos, vel, ages, a_nom, pending, fixed, pn, vn, measured, recorded, braking) in \
            enumerate(_ticks(seed, 50)):
        now = 0.05 * t if with_now else None
        outs = [pred.predict(ids, pos, vel, ages, a_nom, measured, fixed=fixed, pending=pending,
                             position_noise=pn, velocity_noise=vn, now=now) for pred in (compiled, reference)]
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(outs[0], name), getattr(outs[1], name), err_msg=name)
        for name in ("_accel_bound", "_delay_seen", "_jitter_left"):
            np.testing.assert_array_equal(getattr(compiled, name), getattr(reference, name), err_msg=name)
        compiled.record(ids, recorded, braking)
        reference.record(ids, recorded, braking)


def test_the_reference_is_not_the_compiled_code():
    assert NumpyPredictor._listening is not LatencyPredictor._listening


@settings(max_examples=100, deadline=None)
@given(ages=st.lists(st.one_of(st.floats(0.0, 10.0), st.sampled_from([0.0, 0.05, 0.1, 0.15 - 1e-12, np.inf, 1e300])),
                     min_size=1, max_size=8),
       pending=st.integers(-1, 12), measured=st.sampled_from([None, 0.0, 0.07, 0.3]))
def test_compiled_late_equals_numpy_formulation(ages, pending, measured):
    """``late``: more commands pending than the horizon allows, as ``pending > horizon_ticks``."""
    predictor = LatencyPredictor(DYN, LatencyConfig())
    ages = np.array(ages)
    pend = np.full(len(ages), pending, dtype=np.int64)
    delay = max(predictor.config.command_delay_s, measured or 0.0)
    with np.errstate(invalid="ignore"):
        want = pend > horizon_ticks(ages, delay, DYN.dt)
    np.testing.assert_array_equal(predictor.late(ages, pend, measured), want)


def test_late_hand_worked():
    """dt 0.05 s, bound 0.15 s: a fresh state allows 3 pending commands, one 0.1 s old allows 5."""
    predictor = LatencyPredictor(DYN, LatencyConfig(command_delay_s=0.15))
    ages, pending = np.array([0.0, 0.0, 0.1, 0.1]), np.array([3, 4, 5, 6])
    assert predictor.late(ages, pending).tolist() == [False, True, False, True]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 6), ticks=st.integers(1, 12),
       scale=st.sampled_from([0.5, 3.0, 1e200]))
def test_compiled_record_equals_numpy_formulation(seed, n, ticks, scale):
    """``record``: the history shifts one tick older and takes the clipped command, as the numpy
    lines it replaced (``clip_norm``, two slice copies, ``np.minimum`` of the counts)."""
    rng = np.random.default_rng(seed)
    predictor, ids = LatencyPredictor(DYN, LatencyConfig()), tuple(f"r{i}" for i in range(n))
    predictor._align(ids)
    history, braked = predictor._history.copy(), predictor._braked.copy()
    recorded = predictor._recorded.copy()
    for _ in range(ticks):
        accel, braking = rng.normal(0.0, scale, (n, 2)), rng.random(n) < 0.3
        none = rng.random() < 0.2
        predictor.record(ids, accel, None if none else braking)
        given = np.zeros(n, dtype=bool) if none else braking
        history[:-1], braked[:-1] = history[1:].copy(), braked[1:].copy()
        history[-1], braked[-1] = clip_norm(accel, DYN.accel_limit), given
        recorded = np.minimum(recorded + 1, predictor.depth)
        np.testing.assert_array_equal(predictor._history, history)
        np.testing.assert_array_equal(predictor._braked, braked)
        np.testing.assert_array_equal(predictor._recorded, recorded)
