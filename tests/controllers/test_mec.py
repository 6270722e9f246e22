"""Model error compensator: gain against filterpy, step response by hand, gain error, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from controllers.mec import (
    MecConfig,
    MecStatus,
    ModelErrorCompensator,
    observer_model,
    steady_state_gain,
)
from sim.scenario import Dynamics

DYN = Dynamics()                     # dt 0.05 s, damping 0.5 1/s, accel limit 1, speed limit 0.4


def plant(vel, u, dyn=DYN, disturbance=0.0, gain=1.0):
    """The world's velocity step with an actuator gain and an additive disturbance [m/s^2]."""
    return vel + dyn.dt * (gain * u + disturbance - dyn.damping * vel)


def test_steady_state_gain_matches_filterpy():
    f, b, h, q, r = observer_model(DYN, MecConfig())
    kf = KalmanFilter(dim_x=2, dim_z=1, dim_u=1)
    kf.F, kf.B, kf.H, kf.Q, kf.R = f, b, h, q, r
    kf.P *= 10.0
    for _ in range(300):
        kf.predict(u=np.array([[0.0]]))
        kf.update(np.array([[0.0]]))
    np.testing.assert_allclose(steady_state_gain(DYN, MecConfig()), kf.K.ravel(), rtol=1e-8)


def test_step_disturbance_is_tracked_within_two_ticks():
    """Hand-check: from an exact estimate, a step d appears one tick later as the innovation
    e = dt * d (the velocity gained beyond the prediction), so d_hat_1 = K_d * dt * d
    (K_d = 13.72 1/s with the defaults: 0.686 d). The estimator poles (I - K H) F have modulus
    0.339, so the error shrinks by about a third per tick: d_hat is within 5 % of d from the
    second tick on and within 1 % from the fifth."""
    k_v, k_d = steady_state_gain(DYN, MecConfig())
    assert k_d == pytest.approx(13.72, abs=0.01)
    f, _, h, _, _ = observer_model(DYN, MecConfig())
    poles = np.abs(np.linalg.eigvals((np.eye(2) - np.outer([k_v, k_d], h)) @ f))
    np.testing.assert_allclose(poles, 0.339, atol=1e-3)

    mec = ModelErrorCompensator(DYN)
    d = np.array([[0.3, -0.2], [0.0, 0.5]])
    vel = np.zeros((2, 2))
    target = np.zeros((2, 2))
    assert mec.step(vel, target).status is MecStatus.RESET
    u = np.zeros((2, 2))                          # the command sent on the reset tick
    estimates = []
    for _ in range(8):
        vel = plant(vel, u, disturbance=d)
        out = mec.step(vel, target)
        u = out.a_cmd
        estimates.append(out.d_hat)
    np.testing.assert_allclose(estimates[0], k_d * DYN.dt * d, rtol=1e-9)
    for tick, est in enumerate(estimates, start=1):
        err = np.abs(est - d).max() / np.abs(d).max()
        if tick >= 2:
            assert err < 0.05, (tick, err)
        if tick >= 5:
            assert err < 0.01, (tick, err)
    # compensated: the plant now realises the commanded (zero) acceleration
    np.testing.assert_allclose(u, -d, atol=0.01 * np.abs(d).max())


def test_gain_error_is_compensated():
    """A plant achieving 0.7 u: the loop settles at u = a_safe / 0.7, the plant achieves a_safe."""
    mec = ModelErrorCompensator(DYN)
    a_safe = np.array([[0.4, -0.3], [-0.2, 0.1]])
    vel = np.zeros((2, 2))
    achieved = []
    plain_vel = np.zeros((2, 2))
    for _ in range(20):
        u = mec.step(vel, a_safe).a_cmd
        new = plant(vel, u, gain=0.7)
        achieved.append((new - vel) / DYN.dt + DYN.damping * vel)
        vel = new
        plain_vel = plant(plain_vel, a_safe, gain=0.7)
    np.testing.assert_allclose(achieved[-1], a_safe, rtol=0.01)
    np.testing.assert_allclose(achieved[0], 0.7 * a_safe)           # before any estimate
    nominal = np.zeros((2, 2))
    for _ in range(20):
        nominal = plant(nominal, a_safe)
    # the compensated robot ends closer to the nominal model than the uncompensated one
    assert np.abs(vel - nominal).max() < 0.3 * np.abs(plain_vel - nominal).max()


def test_limits_and_bad_input():
    mec = ModelErrorCompensator(DYN, MecConfig(adapt_noise=False))     # compensates from tick 1
    vel = np.zeros((3, 2))
    mec.step(vel, np.zeros((3, 2)))
    # a strong disturbance against a large command: the compensated command is clipped
    vel = plant(vel, np.zeros((3, 2)), disturbance=-0.8)
    out = mec.step(vel, np.full((3, 2), 0.6))
    assert out.status is MecStatus.CLIPPED
    assert np.all(np.linalg.norm(out.a_cmd, axis=1) <= DYN.accel_limit + 1e-12)
    held = out.d_hat.copy()
    bad = vel.copy()
    bad[1] = np.nan
    out = mec.step(bad, np.zeros((3, 2)))
    assert out.status is MecStatus.INVALID_MEASUREMENT and np.all(np.isfinite(out.a_cmd))
    np.testing.assert_allclose(out.d_hat[1], held[1])                    # robot 1 held its estimate
    target = np.zeros((3, 2))
    target[2, 0] = np.inf
    out = mec.step(vel, target)
    assert out.status is MecStatus.INVALID_COMMAND
    np.testing.assert_allclose(out.a_cmd[2], 0.0)
    assert mec.step(np.zeros((4, 2)), np.zeros((4, 2)), ids=("a", "b", "c", "d")).status \
        is MecStatus.RESET                                              # nobody known: afresh
    with pytest.raises(ValueError, match="velocity and a_safe must both have shape"):
        mec.step(np.zeros((4, 2)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="mec.disturbance_rate"):
        MecConfig(disturbance_rate=0.0)


def delayed_plant_run(mec, delay, steps, rng, gain=1.0, noise=0.0):
    """Commands a_safe (random steps every 10 ticks) through a plant that runs each command
    ``delay`` ticks late with actuator ``gain``; returns the MEC results and the velocities."""
    vel = np.zeros((1, 2))
    pipe = [np.zeros((1, 2))] * delay
    target = np.zeros((1, 2))
    results = []
    for k in range(steps):
        if k % 10 == 0:
            target = rng.uniform(-0.5, 0.5, (1, 2))
        measured = vel + rng.normal(0, noise, (1, 2)) if noise else vel
        out = mec.step(measured, target)
        results.append(out)
        pipe.append(out.a_cmd)
        vel = plant(vel, pipe.pop(0), gain=gain)
    return results


@pytest.mark.parametrize("delay", [0, 1, 2, 3])
def test_the_bank_finds_the_command_delay_and_then_estimates_the_gain_error(delay):
    rng = np.random.default_rng(delay)
    results = delayed_plant_run(ModelErrorCompensator(DYN), delay, 120, rng, gain=0.7)
    assert [int(r.delay_ticks[0]) for r in results[-40:]] == [delay] * 40
    # gain 0.7: d = -0.3 u_applied; the loop settles at a_cmd = a_safe / 0.7 (commands steady
    # for 10 ticks: compare on the last tick of each step)
    last = results[-1]
    np.testing.assert_allclose(last.a_cmd * 0.7, last.a_cmd + last.d_hat, atol=0.05)


def test_a_single_delay_free_observer_fed_a_delayed_plant_oscillates_and_the_bank_does_not():
    """Teeth: the old observer (one hypothesis, no delay) reads a one-tick-late command as a
    disturbance and feeds the difference back; its compensation swings far beyond the bank's."""
    swings = {}
    for name, cfg in (("bank", MecConfig()), ("single", MecConfig(max_delay_ticks=0))):
        results = delayed_plant_run(ModelErrorCompensator(DYN, cfg), 1, 120, np.random.default_rng(7))
        swings[name] = max(np.abs(r.d_hat).max() for r in results[20:])
    assert swings["bank"] < 0.05                        # no model error: nothing to compensate
    assert swings["single"] > 4 * swings["bank"] + 0.1


def test_estimates_follow_robot_ids_through_a_leave_and_a_join_in_one_tick():
    mec = ModelErrorCompensator(DYN)
    d = np.array([[0.3, 0.0], [0.0, -0.2]])
    vel, u = np.zeros((2, 2)), np.zeros((2, 2))
    mec.step(vel, np.zeros((2, 2)), ids=("a", "b"))
    for _ in range(12):
        vel = plant(vel, u, disturbance=d)
        u = mec.step(vel, np.zeros((2, 2)), ids=("a", "b")).a_cmd
    # "a" leaves and "c" joins in the same tick, rows reordered: b's estimate goes with b
    out = mec.step(np.array([[0.0, 0.0], vel[1]]), np.zeros((2, 2)), ids=("c", "b"))
    np.testing.assert_allclose(out.d_hat[0], 0.0)                   # c starts afresh
    np.testing.assert_allclose(out.d_hat[1], [0.0, -0.2], atol=0.03)
    assert out.status is not MecStatus.RESET                       # b was known


def test_a_dropped_measurement_keeps_the_estimate_as_of_the_last_one_by_robot_id():
    """A NaN row only predicts: ``update`` returns the prediction to now, ``v_measured`` the
    estimate of the tick the robot's last measurement arrived (what a caller that carries the
    robot on from that measurement itself needs), and it follows the robot's id."""
    mec = ModelErrorCompensator(DYN)
    vel, u = np.array([[0.1, 0.0], [0.0, -0.1]]), np.array([[0.5, 0.0], [0.0, 0.5]])
    mec.step(vel, u, ids=("a", "b"))
    vel = plant(vel, u)
    fresh = mec.update(vel, ids=("a", "b")).copy()
    np.testing.assert_array_equal(mec.v_measured, fresh)
    mec.compensate(u)
    now = mec.update(np.array([[np.nan, np.nan], vel[1] + DYN.dt * 0.5]), ids=("a", "b"))
    assert np.abs(now[0] - fresh[0]).max() > 0.02                  # predicted through u: 0.025 m/s on
    np.testing.assert_array_equal(mec.v_measured[0], fresh[0])
    np.testing.assert_array_equal(mec.v_measured[1], now[1])
    mec.compensate(u)
    again = mec.update(np.array([[np.nan, np.nan], [0.0, 0.0], [np.nan, np.nan]]), ids=("b", "a", "c"))
    np.testing.assert_array_equal(mec.v_measured[0], now[1])      # b lost this one: its last, by id
    np.testing.assert_array_equal(mec.v_measured[1], again[1])    # a measured again, now row 1
    np.testing.assert_array_equal(mec.v_measured[2], 0.0)         # c never measured


def test_velocity_noise_is_measured_and_not_compensated_as_a_disturbance():
    """Teeth: with 2 cm/s of velocity noise (4x the design's 5 mm/s) and no disturbance at all,
    the fixed design gain turns the noise into compensation of several tenths of m/s^2 (a random
    walk for the robot); measuring the noise (about 0.02 m/s here) keeps it near zero, while a
    real gain error at the design noise is still compensated in full (see the bank test)."""
    sizes, measured = {}, None
    for adapt in (False, True):
        mec = ModelErrorCompensator(DYN, MecConfig(adapt_noise=adapt))
        results = delayed_plant_run(mec, 0, 200, np.random.default_rng(3), noise=0.02)
        sizes[adapt] = np.sqrt(np.mean([np.sum(r.compensation**2) for r in results[20:]]))
        measured = np.sqrt(mec.noise_var[0])
    assert sizes[False] > 0.3
    assert sizes[True] < 0.3 * sizes[False]                  # measured: 0.2
    assert measured == pytest.approx(0.02, rel=0.3)


def test_pure_noise_passes_the_threshold_about_once_in_a_million_robot_ticks(monkeypatch):
    """20 robots x 3000 ticks at rest under 2 cm/s of velocity noise, nothing to compensate: the
    norm of ``d_hat``'s wander is Rayleigh, so the 5.26-sigma threshold lets almost none of it
    through (2 of 59,000 robot-ticks here, 3.4e-5: early ticks, before a robot's noise is known);
    the former 4 sigma (exp(-8) = 3e-4 a tick, and the estimate wanders in runs) let through 64,
    1.1e-3."""
    def compensated_fraction() -> float:
        mec, rng, hits = ModelErrorCompensator(DYN), np.random.default_rng(0), 0
        for t in range(3000):
            out = mec.step(rng.normal(0.0, 0.02, (20, 2)), np.zeros((20, 2)))
            hits += int((np.abs(out.compensation).sum(axis=1) > 0).sum()) if t >= 50 else 0
        return hits / (20 * 2950)
    assert compensated_fraction() < 1e-4
    monkeypatch.setattr("controllers.mec.SIGNIFICANCE", 4.0)
    assert compensated_fraction() > 5e-4


def test_a_robot_whose_noise_rests_on_few_samples_is_counted_noisier(monkeypatch):
    """The first ticks of 1000 robots at rest under 2 cm/s of noise (12 ticks each): the noise
    level counted is its estimate plus ``NOISE_UPPER_SIGMAS`` = 3 standard deviations of it, so
    42 robot-ticks of 12,000 compensate wander (measured); with 2 standard deviations (the rule
    before) lucky residual changes read a noisy robot as quiet 63 times, and the MEC tracked
    0.50 mm against 0.43 without it under pure noise (``tracking_error_mm("noise", 12, 0)``)."""
    def compensated() -> int:
        hits = 0
        for seed in range(10):
            mec, rng = ModelErrorCompensator(DYN), np.random.default_rng(seed)
            for _ in range(12):
                out = mec.step(rng.normal(0.0, 0.02, (100, 2)), np.zeros((100, 2)))
                hits += int((np.abs(out.compensation).sum(axis=1) > 0).sum())
        return hits
    assert compensated() <= 50
    monkeypatch.setattr("controllers.mec.NOISE_UPPER_SIGMAS", 2.0)
    assert compensated() >= 58


@pytest.mark.parametrize("glitch", [1e3, 1e160])
def test_one_impossible_velocity_reading_is_no_measurement_and_the_robot_is_compensated_again(glitch):
    """Before: a reading of 1e160 m/s overflowed the innovation score to inf, gating the robot
    for good; one of 1000 m/s held its noise estimate up past the end of a 20 s run. Both now
    count as no measurement, as NaN does, and the run matches a run with a NaN there."""
    dyn = Dynamics()

    def run(reading):
        mec, v, out = ModelErrorCompensator(dyn), np.zeros((1, 2)), []
        for k in range(400):
            res = mec.step(np.array([[reading, 0.0]]) if k == 50 else v.copy(), np.array([[0.2, 0.0]]))
            if k == 50:
                assert res.status == MecStatus.INVALID_MEASUREMENT
            v = np.clip(v + dyn.dt * (0.7 * res.a_cmd - dyn.damping * v), -0.4, 0.4)   # gain 0.7
            out.append((bool(res.gated[0]), res.compensation[0].copy()))
        return out

    got, want = run(glitch), run(np.nan)
    assert not any(gated for gated, _ in got[51:])
    assert got[-1][1][0] < -0.05                        # compensating the 0.7 gain again
    np.testing.assert_array_equal(np.array([c for _, c in got]), np.array([c for _, c in want]))
