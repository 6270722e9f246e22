"""Episodes of a :class:`stack.pipeline.ControlStack` on any :class:`sim.fleet.Fleet`.

:func:`run_episode` drives a fleet with a stack and judges the episode with :mod:`sim.metrics`
(success, final distance, collisions), plus the stack's own counters (interventions, slack,
fallback, braking) and the nominal-model tracking error (see :func:`nominal_step`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from sim.fleet import Fleet, FleetState
from sim.metrics import collision_events, episode_outcome
from sim.scenario import Dynamics

if TYPE_CHECKING:
    from stack.pipeline import ControlStack
    from stack.recorder import EpisodeRecorder


def nominal_step(pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
                 dynamics: Dynamics) -> tuple[np.ndarray, np.ndarray]:
    """One tick of the nominal model (:class:`sim.scenario.Dynamics`, no error, no contact).

    ``a = clip_norm(acc, accel_limit)``, ``v' = clip_norm(v + dt (a - c v), speed_limit)``,
    ``p' = p + dt v'``; (N, 2) arrays in m, m/s, m/s^2 -> (p', v').
    """
    return dynamics.step_np(pos, vel, acc)


@dataclass
class EpisodeMetrics:
    """One episode of a stack on a fleet.

    Attributes:
        success: every robot within tolerance of its assigned target at the end, no collision.
        final_distance: mean assigned robot-target distance at the end [m].
        collided: any collision onset during the episode.
        robot_collisions, object_collisions, wall_collisions: collision onsets per kind.
        steps: ticks run.
        interventions, infeasible, fallbacks, braking: ticks with that event (see TickResult).
        tracking_error: mean one-tick position error [m] of the fleet against the nominal model
            driven by ``a_safe`` from the measured state (:func:`nominal_step`); what the MEC
            drives towards 0.
        p50_tick_ms, p99_tick_ms: tick latency percentiles [ms].
        arrival_step: the first tick count t (1..steps) after which every robot stood within
            ``target_tolerance`` of its assigned target (the true state where the fleet has one,
            collisions aside); None if that never happened. How fast a layer lets the team
            arrive, which success at the end does not show.
    """

    success: bool
    final_distance: float
    collided: bool
    robot_collisions: int
    object_collisions: int
    wall_collisions: int
    steps: int
    interventions: int
    infeasible: int
    fallbacks: int
    braking: int
    tracking_error: float
    p50_tick_ms: float
    p99_tick_ms: float
    arrival_step: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _all_within(fleet: Fleet, state: FleetState, tolerance: float) -> bool:
    """Every robot within ``tolerance`` of its assigned target (the fleet's true state if it
    has one); the optimal assignment runs only when every robot has some target that near."""
    true_state = getattr(fleet, "true_state", None)
    if true_state is not None:
        state = true_state()
    gaps = np.linalg.norm(state.positions[:, None] - state.targets[None], axis=-1)    # (N, N)
    if not (gaps.min(1) <= tolerance).all():
        return False
    outcome = episode_outcome(torch.from_numpy(state.positions)[None], torch.from_numpy(state.targets)[None],
                              torch.tensor([False]), tolerance)
    return bool(outcome.success[0])


def _contact_rows(fleet: Fleet, state: FleetState) -> np.ndarray:
    """(N, 3) bool robot / object / wall contact of a self-judging fleet now (its ``contacts``,
    :class:`sim.pymunk_world.Contacts`; none known: all False)."""
    contacts = getattr(fleet, "contacts", None)
    if contacts is None:
        return np.zeros((state.num_robots, 3), dtype=bool)
    return np.stack((contacts.robot, contacts.object, contacts.wall), -1)


def run_episode(fleet: Fleet, stack: ControlStack, seed: int | None, steps: int | None = None,
                *, start: Callable[[Fleet], FleetState] | None = None,
                recorder: EpisodeRecorder | None = None) -> EpisodeMetrics:
    """Reset ``fleet`` with ``seed`` and run ``steps`` ticks (default: the scenario's episode).

    Collisions: a fleet with ``collision_counts`` and ``outcome()`` (the pymunk world) judges
    itself on its true state; any other fleet is judged here with :mod:`sim.metrics` on the
    state it reports. ``start(fleet)``, if given, runs after the reset (e.g. to place robots)
    and returns the first state. ``recorder`` (:class:`stack.recorder.EpisodeRecorder`), if
    given, records every tick; its :meth:`~stack.recorder.EpisodeRecorder.finish` is the caller's.
    """
    scenario = fleet.scenario
    steps = scenario.dynamics.episode_steps if steps is None else steps
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    state = fleet.reset(seed=seed)
    if start is not None:
        state = start(fleet)
    stack.reset()
    if recorder is not None:
        recorder.start(fleet, state)
    self_judging = hasattr(fleet, "collision_counts") and hasattr(fleet, "outcome")
    polygon = torch.as_tensor(scenario.polygon, dtype=torch.float64)
    prev_contact = np.zeros((state.num_robots, 3), dtype=bool)
    counts = np.zeros(3, dtype=np.int64)
    counters = dict.fromkeys(("interventions", "infeasible", "fallbacks", "braking"), 0)
    tracking, latency = [], []
    arrival_step = None
    for step in range(steps):
        tick = stack.tick(state)
        latency.append(tick.timings_ns["total"])
        counters["interventions"] += tick.intervened
        counters["infeasible"] += tick.infeasible
        counters["fallbacks"] += tick.fallback
        counters["braking"] += tick.braking
        predicted, _ = nominal_step(state.positions, state.velocities, tick.a_safe, scenario.dynamics)
        fleet.send_accelerations(tick.a_cmd)
        given, state = state, fleet.step()
        tracking.append(float(np.linalg.norm(state.positions - predicted, axis=1).mean()))
        if arrival_step is None and _all_within(fleet, state, scenario.target_tolerance):
            arrival_step = step + 1
        if not self_judging:
            ev = collision_events(torch.from_numpy(state.positions)[None], polygon,
                                  scenario.robot_radius, scenario.arena)
            contact = torch.stack((ev.robot[0], ev.object[0], ev.wall[0]), -1).numpy()
            counts += (contact & ~prev_contact).sum(0)
            prev_contact = contact
        if recorder is not None:
            recorder.tick(given, tick, fleet, state, contact if not self_judging else _contact_rows(fleet, state))
        braked = getattr(fleet, "braked_in_place", None)          # a fleet over a bridge
        braked = braked(given) if braked is not None else None
        if braked is not None:
            stack.sent_braking(given, braked)
            if recorder is not None:
                recorder.link_braked(given, braked, stack.brake(given.velocities))
    if self_judging:
        c = fleet.collision_counts
        counts = np.array([c.robot, c.object, c.wall])
        outcome = fleet.outcome()
    else:
        outcome = episode_outcome(torch.from_numpy(state.positions)[None],
                                  torch.from_numpy(state.targets)[None],
                                  torch.tensor([bool(counts.sum() > 0)]), scenario.target_tolerance)
    lat = np.asarray(latency) / 1e6
    return EpisodeMetrics(
        success=bool(outcome.success[0]), final_distance=float(outcome.final_distance[0]),
        collided=bool(counts.sum() > 0), robot_collisions=int(counts[0]),
        object_collisions=int(counts[1]), wall_collisions=int(counts[2]), steps=steps,
        tracking_error=float(np.mean(tracking)) if tracking else math.nan,
        p50_tick_ms=float(np.percentile(lat, 50)), p99_tick_ms=float(np.percentile(lat, 99)),
        arrival_step=arrival_step, **counters)
