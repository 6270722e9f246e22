"""ModelError: how a real robot departs from the nominal model (actuator, disturbance, link).

The knobs of :class:`sim.pymunk_world.PymunkWorld`, validated on construction with errors that
name the field; that module's docstring gives the dynamics and the link they drive. The batched
world's actuator (:mod:`sim.actuator`) applies ``gain``, ``gain_spread``, ``lag_tau`` and
``delay_ticks`` by the same law.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.scenario import Scenario


@dataclass(frozen=True)
class ModelError:
    """How a real robot departs from the nominal model; the defaults are a perfect robot.

    Attributes:
        gain: achieved / commanded acceleration (0.7 = the robot reaches 70 %).
        gain_spread: per-robot gain drawn at reset from U(gain - spread, gain + spread).
        lag_tau: first-order actuator lag time constant [s] (0 = none).
        delay_ticks: pure command delay in control ticks (0 = none).
        disturbance: constant acceleration disturbance (x, y) added to every robot [m/s^2].
        disturbance_std: std of a white acceleration disturbance per axis and tick [m/s^2].
        floor_friction: Coulomb-like deceleration opposing motion [m/s^2].
        position_noise_std: measurement noise std per axis on positions [m].
        velocity_noise_std: measurement noise std per axis on velocities [m/s].
        delay_jitter_ticks: extra delay of each command, uniform in 0..this many ticks; the
            robot applies the newest command that has arrived (0 = none).
        state_drop: probability that a robot's measurement of a tick is lost on the way [0, 1).
        freeze: ``(robot row, tick)``: that robot goes silent and deaf from that tick on (see
            :mod:`sim.pymunk_world`), or None.
        playout_ticks: not an error but the robot's remedy for jitter, a playout buffer: it
            acts on command j no earlier than tick j + playout_ticks, so any delay up to that
            becomes exactly that (0 = act on arrival). Its robot runtime can do the same with
            the CMD's ``state_seq``: the robot tick the command answers.
        adaptive_playout: the playout delay of each robot is the largest command delay it has
            seen this episode (arrival tick - the tick the command answers), at least
            ``playout_ticks``: a jittering delay becomes its maximum without configuring it,
            and a constant delay stays as it is (no latency added). It only grows, so it
            never skips a command; an increase holds one command an extra tick.
    """

    gain: float = 1.0
    gain_spread: float = 0.0
    lag_tau: float = 0.0
    delay_ticks: int = 0
    disturbance: tuple[float, float] = (0.0, 0.0)
    disturbance_std: float = 0.0
    floor_friction: float = 0.0
    position_noise_std: float = 0.0
    velocity_noise_std: float = 0.0
    delay_jitter_ticks: int = 0
    state_drop: float = 0.0
    freeze: tuple[int, int] | None = None
    playout_ticks: int = 0
    adaptive_playout: bool = False

    def __post_init__(self) -> None:
        def number(name: str, value) -> float:
            if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
                raise ValueError(f"ModelError.{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"ModelError.{name} must be finite, got {value!r}")
            return float(value)

        for name in ("gain_spread", "lag_tau", "disturbance_std", "floor_friction",
                     "position_noise_std", "velocity_noise_std"):
            if number(name, getattr(self, name)) < 0:
                raise ValueError(f"ModelError.{name} must be >= 0 (0 turns it off), "
                                 f"got {getattr(self, name)!r}")
        if number("gain", self.gain) <= 0:
            raise ValueError(f"ModelError.gain must be > 0 (1 = perfect actuator), got {self.gain!r}")
        if self.gain - self.gain_spread <= 0:
            raise ValueError(f"ModelError.gain_spread = {self.gain_spread!r} must be below gain = "
                             f"{self.gain!r} so that every robot's gain stays positive")
        for name in ("delay_ticks", "delay_jitter_ticks", "playout_ticks"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
                raise ValueError(f"ModelError.{name} must be an integer >= 0, got {value!r}")
        if not isinstance(self.adaptive_playout, bool | np.bool_):
            raise ValueError(f"ModelError.adaptive_playout must be true or false, got {self.adaptive_playout!r}")
        if not 0 <= number("state_drop", self.state_drop) < 1:
            raise ValueError(f"ModelError.state_drop must be a probability in [0, 1), "
                             f"got {self.state_drop!r}")
        if self.freeze is not None:
            try:
                robot, tick = (int(x) for x in self.freeze)
            except (TypeError, ValueError):
                robot = tick = -1
            if robot < 0 or tick < 0:
                raise ValueError(f"ModelError.freeze must be (robot row >= 0, tick >= 0) or None, "
                                 f"got {self.freeze!r}")
            object.__setattr__(self, "freeze", (robot, tick))
        try:
            dist = tuple(self.disturbance)
        except TypeError:
            dist = ()
        if len(dist) != 2:
            raise ValueError(f"ModelError.disturbance must be an (x, y) pair in m/s^2, "
                             f"got {self.disturbance!r}")
        object.__setattr__(self, "disturbance",
                           (number("disturbance", dist[0]), number("disturbance", dist[1])))

    def check_team(self, scenario: Scenario) -> None:
        """ValueError unless the fields that name a robot (``freeze``) name one of ``scenario``'s."""
        n = scenario.num_robots
        if self.freeze is not None and self.freeze[0] >= n:
            raise ValueError(f"ModelError.freeze (--model-error freeze=ROBOT:TICK) names robot row "
                             f"{self.freeze[0]}, but {scenario.name} has {n} robots: pick a row in 0..{n - 1}")


__all__ = ["ModelError"]
