r"""Where a robot that stopped reporting can be, from the commands it was actually sent.

A robot whose state has gone stale (silent, frozen, its updates lost) is an obstacle of the
safety filter (:mod:`controllers.safety.latency`). :func:`~controllers.safety.reach.reach`
bounds where it can be from its last state and the largest acceleration it may have been
asked: a ball that ignores what was asked. A policy near its target asks for small or
alternating accelerations, and the ball then grows a robot at rest into a disc of 100-280 mm
(measured on the frozen-robot condition of ``bench/safety.py``), which keeps its neighbours
off their own targets. The controller knows better: it kept every command it sent.

**The contract.** A robot acts only on commands it was sent, in the order they were sent, one
a tick, and brakes with the one braking law (:meth:`sim.scenario.Dynamics.brake`) when they
stop: on a BRAKE, or on its own watchdog at most ``W`` ticks after the last command it heard.
The controller sends BRAKE to a robot from the tick its state goes stale. With ``m`` the
commands sent after the newest one the robot had acted on when its last state was measured
(the wire's ``last_cmd_seq``; unknown: every ``m`` the latency bound allows), the commands the
robot may still act on are the last ``m`` it was sent, ``u_1 .. u_m`` (oldest first), and the
one it was acting on, ``u_0``. It may stop hearing after any of them. So it follows one of the
*branches* ``(s, w)``, ``0 <= s <= m``, ``0 <= w <= W``::

    ticks 1..s:          act on u_1 .. u_s          (a BRAKE among them: the braking law)
    ticks s+1..s+w:      hold u_s                   (u_0 when s = 0): deaf, before its watchdog
    then:                the braking law, to rest

each run through the nominal model (:meth:`sim.scenario.Dynamics.step_np`) from the last state
``(p_0, v_0)``. The path of branch ``b`` gives ``P_b(n)``, its centre after ``n`` ticks.

**What the branches cannot know.** The achieved acceleration differs from the asked one by up
to ``A`` per tick (``accel_uncertainty``, plus the weighted spread of the commands for a robot
whose delay jitters, as in :mod:`controllers.safety.latency`; at least ``a_u`` below) while
the robot acts on commands, at most ``K = m + W`` ticks, which moves a centre by
``A dt^2 k (k + 1) / 2`` and its velocity by ``e_v = A dt k`` after ``k = min(n, K)`` ticks. The braking law feeds back the robot's own
velocity, so braking removes a velocity error within ``S`` ticks (the time to stop from the
largest speed of any branch plus ``e_v``), moving the centre by at most ``e_v dt`` a tick
until then; braking itself may miss by ``a_u`` (``accel_uncertainty``) at full braking, in
proportion below it (a robot at rest stays at rest: the wire contract's "brake, hold at
rest"), for those ticks::

    e(n) = A dt^2 k (k + 1) / 2 + e_v dt j + a_u dt^2 j (j + 1) / 2,   j = min(max(n - K, 0), S)

Between ticks a centre moves along a straight segment.

**The disc.** At time ``t`` after the last state, ``n_lo = floor(t / dt)``,
``n_hi = n_lo + 1``: the disc around the centre ``c(t)`` of the bounding box of every
``P_b(n_lo)`` and ``P_b(n_hi)`` with radius ``R(t) = max_b,n |P_b(n) - c(t)| + e(n_hi)`` holds
the robot's centre; its velocity is ``(c(t + dt) - c(t)) / dt`` and its growth rate
``max(R(t + dt) - R(t), 0) / dt``, so the disc one tick on lies inside the disc moved by them.
After ``T`` ticks the disc is fixed: a robot silent for good is an obstacle where it stopped.
(``e(n)`` itself stops growing only after ``K + S`` ticks, which may come later: the disc takes
``e`` of the tick it is asked for, not of ``T``.)

**The cover.** The branches differ mostly in how long the robot went on before it braked, so
their rest points lie along its heading, and one disc round them has a radius of half that
line however thin it is. Once every branch is at rest and ``e(n)`` final (:attr:`settled_s`),
the robot lies within ``e`` of the rest point of the branch it took, so a few discs round groups
of rest points hold it as surely as the one disc (:meth:`SilentPaths.cover`); the filter takes
them as fixed obstacles (:meth:`controllers.safety.prediction.Prediction.with_covers`). Traced on
the frozen-robot condition: rest points 86 mm along the heading and 5 mm across, a 56 mm disc
round a robot 8 mm from its centre, which held a neighbour off the way to its own target.

**Seen at rest.** A tracker over the arena that identifies robots (motion capture) may report
a silent robot as a disc (:class:`Sighting`). Its word alone bounds where the robot was, not
where it goes: a tracker reports how fast it saw a robot move, not how fast a robot that still
acts on commands may move next. Once every branch is at rest (:attr:`SilentPaths.settled_s`)
the robot's contract says it stays at rest, so a sighting taken from then on
(:meth:`SilentPaths.seen_at_rest`) holds it for good. The robot then lies in both the cover
and the sighting's disc, so in the cover's discs that meet the sighting's (:func:`narrowed`):
the near end of the branches, where the robot would be had it stopped at once, is no longer
kept free of neighbours when the tracker sees it at the far end. Where the sighting's one disc
is smaller than what is left of the cover (by area), it is the bound instead.

Measured on the frozen-robot condition (a robot that goes silent and deaf mid-episode, its
watchdog braking it two ticks later), 80 episodes of a 3-5 robot policy: the ball's radius at
the end of an episode was 7-283 mm for robots whose true centre lay 0.5-44 mm from the ball's
centre; the branches' disc is 10-74 mm, the true centre 0.2-15 mm from its centre.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim.scenario import Dynamics


def branch_paths(pos0: np.ndarray, vel0: np.ndarray, commands: np.ndarray, braking: np.ndarray,
                 hold_ticks: int, dynamics: Dynamics) -> np.ndarray:
    """Centres along every branch ``(s, w)`` of the module docstring.

    Args:
        pos0, vel0: (2,) the last state [m], [m/s].
        commands: (m + 1, 2) ``u_0 .. u_m`` [m/s^2], oldest first (``u_0``: acting at the last state).
        braking: (m + 1,) bool, commands that were BRAKE (the robot applies the braking law).
        hold_ticks: ``W``, the most ticks a deaf robot holds its last command.

    Returns:
        (B, T + 1, 2) centres [m] for ``B = (m + 1) (W + 1)`` branches, ``T`` ticks after the
        last state (row 0: ``pos0``), every branch at rest by tick ``T``.
    """
    m = len(commands) - 1
    s = np.repeat(np.arange(m + 1), hold_ticks + 1)
    w = np.tile(np.arange(hold_ticks + 1), m + 1)
    stop_ticks = int(np.ceil(dynamics.speed_limit / (dynamics.accel_limit * dynamics.dt))) + 2
    ticks = m + hold_ticks + stop_ticks
    n_branches = len(s)
    p = np.broadcast_to(pos0, (n_branches, 2)).copy()
    v = np.broadcast_to(vel0, (n_branches, 2)).copy()
    out = np.empty((n_branches, ticks + 1, 2))
    out[:, 0] = p
    for n in range(1, ticks + 1):
        index = np.where(n <= s, n, s)                      # acting on u_n, or holding u_s
        acting = n <= s + w
        brakes = ~acting | braking[index]
        accel = np.where(brakes[:, None], dynamics.brake(v), commands[index])
        p, v = dynamics.step_np(p, v, accel)
        out[:, n] = p
    return out


@dataclass(frozen=True)
class Sighting:
    """A tracker's sighting of one robot as a fixed filter row: ``centre`` (2,) [m], ``grow``
    [m] and ``closing`` [m/s] as in :class:`controllers.safety.prediction.Prediction` (the
    tracker's radius beyond the robot's and its speed bound over the reach, as an obstacle's:
    :meth:`~controllers.safety.prediction.Prediction.with_obstacles`), ``taken_at`` [s] on the
    states' clock."""

    centre: np.ndarray
    grow: float
    closing: float
    taken_at: float


@dataclass(frozen=True)
class SilentPaths:
    """The branches of one robot from one last state (module docstring).

    Attributes:
        measured_at: when that state was measured [s] (a newer state makes these paths stale).
        points: (B, T + 1, 2) centres along the branches [m].
        accel_error: ``A`` [m/s^2] while acting on commands; ``brake_error``: ``a_u`` while braking.
        acting_ticks: ``K``; ``stop_ticks``: ``S``.
        dt: the control tick [s].
    """

    measured_at: float
    points: np.ndarray
    accel_error: float
    brake_error: float
    acting_ticks: int
    stop_ticks: int
    dt: float
    _covers: dict = field(default_factory=dict, compare=False, repr=False)   # (merge, most) -> cover

    def error(self, n: int) -> float:
        """``e(n)`` [m], the module docstring's bound after ``n`` ticks."""
        k = min(n, self.acting_ticks)
        j = min(max(n - self.acting_ticks, 0), self.stop_ticks)
        dt2 = self.dt * self.dt
        acting = max(self.accel_error, self.brake_error)   # a branch may brake within the K ticks
        return acting * dt2 * (k * (k + 1) / 2 + k * j) + self.brake_error * dt2 * j * (j + 1) / 2

    def _disc(self, t: float) -> tuple[np.ndarray, float]:
        last = self.points.shape[1] - 1
        tick = int(np.floor(t / self.dt + 1e-9))
        lo = min(tick, last)
        hi = min(lo + 1, last)
        centre, spread = _box_disc(self.points[:, lo:hi + 1].reshape(-1, 2))
        return centre, spread + self.error(tick + 1)     # e(n) grows past T while braking absorbs e_v

    @property
    def settled_s(self) -> float:
        """[s] after the last state from which the robot is at rest whatever its branch: every
        branch stopped (``T`` ticks) and ``e(n)`` at its final value (``K + S`` ticks)."""
        return max(self.points.shape[1] - 1, self.acting_ticks + self.stop_ticks) * self.dt

    def seen_at_rest(self, taken_at: float) -> bool:
        """Whether a picture taken at ``taken_at`` [s] (the states' clock) saw the robot at
        rest for good: no earlier than :attr:`settled_s` after its last state (module
        docstring, Seen at rest)."""
        return taken_at + 1e-9 >= self.measured_at + self.settled_s

    def cover(self, t: float, merge: float, most: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Discs whose union holds the robot ``t`` seconds after the last state, once it is
        :attr:`settled_s` (None before): ``(centres (C, 2) [m], radii (C,) [m])``, ``C <= most``.

        The robot's centre lies within ``e`` of the rest point of the branch it took (module
        docstring), so the union of the discs of radius ``e`` round the ``B`` rest points holds
        it. Rest points that lie along the robot's heading (the branches differ in how long it
        went on) make a line that the one disc of :meth:`disc` covers with a radius of half its
        length (traced: 86 mm of rest points, a 56 mm disc round a robot 8 mm from its centre).
        Here the rest points, in order along their widest axis, are grouped greedily while a
        group's bounding-box centre lies within ``merge`` of each of its points (``merge``
        doubled until at most ``most`` groups), each group a disc of radius ``e`` plus its spread.
        """
        if t + 1e-9 < self.settled_s:
            return None
        key = (float(merge), int(most))            # settled: e(n) final, the cover fixed
        if key not in self._covers:
            self._covers[key] = self._cover(self.error(int(np.floor(t / self.dt + 1e-9)) + 1), *key)
        return self._covers[key]

    def _cover(self, error: float, merge: float, most: int) -> tuple[np.ndarray, np.ndarray]:
        rest = self.points[:, -1]
        lo, hi = rest.min(axis=0), rest.max(axis=0)
        merge = max(float(merge), 1e-6)
        order = np.argsort(rest[:, int(np.argmax(hi - lo))], kind="stable")
        while True:
            groups, start = [], 0
            for k in range(1, len(order) + 1):
                if k < len(order) and _box_disc(rest[order[start:k + 1]])[1] <= merge:
                    continue
                groups.append(_box_disc(rest[order[start:k]]))
                start = k
            if len(groups) <= most:
                break
            merge *= 2.0
        return np.array([c for c, _ in groups]), np.array([r for _, r in groups]) + error

    def disc(self, t: float) -> tuple[np.ndarray, np.ndarray, float, float]:
        """``(centre (2,), centre velocity (2,), radius, growth rate)`` at ``t`` seconds after
        the last state [m, m/s, m, m/s] (module docstring, The disc)."""
        centre, radius = self._disc(t)
        ahead, radius_ahead = self._disc(t + self.dt)
        return centre, (ahead - centre) / self.dt, radius, max(radius_ahead - radius, 0.0) / self.dt


def narrowed(cover: tuple[np.ndarray, np.ndarray], sighting: Sighting
             ) -> tuple[tuple[np.ndarray, np.ndarray], float]:
    """``((centres (C, 2), grow (C,)), closing)``: the discs that hold a robot at rest that lies
    both in ``cover`` (centres (K, 2) [m], grow (K,) [m]) and in the sighting's disc, and the
    speed [m/s] its row closes at (module docstring, Seen at rest): the cover's discs that meet
    the sighting's, or the sighting's disc where its area is the smaller (closing: the
    sighting's speed; else inf, the caller's). Where no cover disc meets it, one of the two
    pictures is wrong: both are kept."""
    centres, radii = cover
    meet = np.linalg.norm(centres - sighting.centre, axis=1) <= radii + sighting.grow
    own = (sighting.centre[None], np.array([sighting.grow]))
    if not meet.any():
        return (np.vstack([centres, own[0]]), np.concatenate([radii, own[1]])), np.inf
    if sighting.grow ** 2 <= (radii[meet] ** 2).sum():
        return own, sighting.closing
    return (centres[meet], radii[meet]), np.inf


def _box_disc(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The centre of the bounding box of (K, 2) points [m] and the largest distance of a point
    from it [m]: a disc holding them all."""
    centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
    return centre, float(np.sqrt(((points - centre) ** 2).sum(axis=1)).max())


def silent_paths(pos0: np.ndarray, vel0: np.ndarray, sequences: list[tuple[np.ndarray, np.ndarray]],
                 hold_ticks: int, accel_error: float, brake_error: float, measured_at: float,
                 dynamics: Dynamics) -> SilentPaths:
    """:class:`SilentPaths` over the branches of every ``(commands, braking)`` sequence given
    (one per pending count the link allows, see :func:`branch_paths`)."""
    paths = [branch_paths(pos0, vel0, commands, braking, hold_ticks, dynamics) for commands, braking in sequences]
    length = max(x.shape[1] for x in paths)
    points = np.concatenate([np.concatenate([x, np.repeat(x[:, -1:], length - x.shape[1], axis=1)], axis=1)
                             for x in paths])
    acting = max(len(commands) for commands, _ in sequences) - 1 + hold_ticks
    speed = float(np.hypot(*np.diff(points, axis=1).transpose(2, 0, 1)).max(initial=0.0)) / dynamics.dt
    velocity_error = accel_error * dynamics.dt * acting
    stop = int(np.ceil((speed + velocity_error) / (dynamics.accel_limit * dynamics.dt) - 1e-9)) + 1
    return SilentPaths(measured_at=float(measured_at), points=points, accel_error=accel_error,
                       brake_error=brake_error, acting_ticks=acting, stop_ticks=stop, dt=dynamics.dt)


__all__ = ["Sighting", "SilentPaths", "branch_paths", "narrowed", "silent_paths"]
