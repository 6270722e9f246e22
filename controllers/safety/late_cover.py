r"""A robot whose state is late: it follows its commands, or it stopped acting on them.

The latency prediction (:mod:`controllers.safety.latency`) runs a robot through the commands it
had yet to act on when it was measured. A state that arrives a tick or more late cannot tell
why it is late: the link lost the robot's updates and the robot goes on obeying, or the robot
froze (silent and deaf: it holds its last command until its watchdog brakes it). Until its
state is older than ``stale_after_s`` the prediction alone took the first; once stale the robot
becomes an obstacle bounded by the branches of the commands it was sent
(:mod:`controllers.safety.silent_reach`), which take the second into account. In between, a
neighbour could come up to the listening disc of a robot that had frozen elsewhere, and the
branches' disc then jumped round it. Traced on ``bench/safety.py`` seed 130 of gain 0.7, two
ticks of delay and a frozen robot: for the two late ticks the frozen robot's disc was 4-7 mm;
on the first stale tick it grew to 44 mm round a neighbour 19 mm away, whose brake, acting two
ticks late at 70 %, could not keep it off (0.26 mm of contact).

**Two hypotheses.** For a robot whose state is late (age at least one tick) but not stale:

* *listening*: the prediction through its pending commands, centre ``p``, velocity ``v``,
  growth ``g_1`` and approach allowance ``c_1`` (:mod:`controllers.safety.latency`, Prediction
  and Tightening);
* *stopped*: the obstacle it will be once stale, from the same last state: the disc of its
  branches (centre ``c_2``, centre velocity ``w_2``, growth ``g_2 = R + sigma_p``, allowance
  ``c_2' = dR/dt + sigma_v``), or the ball of :func:`~controllers.safety.reach.reach` where the
  history lacks the commands it may act on. The branches hold the robot whichever command it
  stopped after (the one it was acting on when measured included) and however long it held it
  before braking. The disc is taken at the time the listening prediction is for, ``m_i`` ticks
  after the state (``h_i`` where the pending count is unknown), not at ``tau + L`` as a stale
  robot's: on a link without command delay that ran the stopped disc up to three ticks ahead
  of the listening centre, and with a fifth of the states dropped (``bench/safety.py``
  ``drops``) the scripted controller then succeeded in 94 of 120 paper-3/4/5 episodes, against
  120 without the cover; taken at ``m_i``, in 120.

**One disc for both.** The row keeps the listening centre and velocity (where the robot's new
command acts if it listens: its own rows and its braking are those of the prediction) and
grows its disc to hold the stopped one::

    g = max(g_1, |c_2 - p| + g_2)

The approach allowance keeps the stopped disc inside one tick on: that disc then lies in the
disc round ``c_2 + w_2 dt`` of radius ``g_2 + c_2' dt`` (the definition of ``w_2`` and ``c_2'``,
:mod:`controllers.safety.silent_reach`, The disc), and the row's disc has moved by ``v dt`` and
grown by ``c dt``, so::

    c = max(c_1, (|c_2 - p + (w_2 - v) dt| + g_2 - g) / dt + c_2')

Where the listening disc holds the stopped one with room to spare, the room is taken off the
allowance (it never goes below ``c_1``), so a late robot whose branches stay within its
listening disc costs its neighbours nothing. Where a neighbour follows the robot, the allowance
does the work: the stopped disc falls behind the listening one at their difference in
velocity, which the growth alone does not see (a neighbour thrusting at a robot frozen at
0.3 m/s from 30 mm behind, gain 0.7, two ticks of delay: 0.3 mm of contact with the growth
alone or without the cover, 32 mm of gap with both; ``tests/controllers/safety/test_late_cover.py``). The robot is still commanded and its rows still
count on its braking: were it stopped, its command would not act, but its disc and allowance
hold it wherever it goes meanwhile, and from the tick it is stale its rows count on the
neighbours' braking alone, as before; what changes is that the disc is no longer smaller than
the obstacle it may turn out to be.
"""

from __future__ import annotations

import numpy as np


def cover_both(pos: np.ndarray, vel: np.ndarray, grow: np.ndarray, closing: np.ndarray,
               centre: np.ndarray, centre_vel: np.ndarray, grow_stopped: np.ndarray,
               closing_stopped: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``(g, c)`` (K,) of the module docstring: the growth [m] and approach allowance [m/s] of K
    late robots' rows that cover them listening and stopped.

    Args:
        pos, vel: (K, 2) the listening prediction ``p``, ``v`` [m], [m/s]; grow, closing: (K,)
            its ``g_1`` [m], ``c_1`` [m/s].
        centre, centre_vel: (K, 2) the stopped disc's ``c_2``, ``w_2``; grow_stopped,
            closing_stopped: (K,) its ``g_2`` [m], ``c_2'`` [m/s].
        dt: the control tick [s].
    """
    offset = centre - pos
    ahead = offset + (centre_vel - vel) * dt
    g = np.maximum(grow, np.hypot(offset[:, 0], offset[:, 1]) + grow_stopped)
    c = np.maximum(closing, (np.hypot(ahead[:, 0], ahead[:, 1]) + grow_stopped - g) / dt + closing_stopped)
    return g, c


__all__ = ["cover_both"]
