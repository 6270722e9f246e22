"""Part (e) of bench/safety.py: intruders a tracker sees (people crossing, boxes on the floor).

Each episode is paper-3, -4 or -5 (by seed) in pymunk under one link condition of
:data:`_safety_conditions.CONDITIONS` (``clean``, ``delay2``, ``noise``, ...), with one to three
random intruders (:func:`random_intruders`): walkers that enter from a random side at a random
tick and cross the arena at 0.05-0.3 m/s, and boxes that stand on the floor from the start, each
of radius 0.03-0.08 m, reported by a tracker that sees them exactly, two ticks late
(:class:`sim.intruders.IntruderFleet`). The scripted controller (and ``--policy``) runs once
through the default stack and once bare (filter off, MEC off) on the same seed. Per condition:
episodes in which a robot drove into an intruder (:class:`sim.intruders.IntruderWatch`) and the
fastest it did, contact episodes among robots, object and walls, success (``success_clear``:
and no robot drove into an intruder), and how close robots came to intruders.

A walker enters where the tracker first sees it, at the arena's edge, so it may step in beside
a robot closer than that robot's braking distance (0.08 m from the 0.4 m/s speed limit, plus two
ticks of sighting age): such a robot brakes and still moves towards it for a few ticks.
"""

from __future__ import annotations

import numpy as np
from _common import map_episodes
from _safety_conditions import CONDITIONS, paired_task_runs

from sim.intruders import Intruder, IntruderFleet
from sim.scenario import Scenario
from stack.pipeline import StackConfig

SIGHTING_DELAY_TICKS = 2


def _walker(rng: np.random.Generator, sc: Scenario, radius: float) -> Intruder:
    """From a random point just outside a random side, towards a random point of the arena's
    middle half, at 0.05-0.3 m/s; it leaves once past the far side."""
    w, h = sc.arena
    side = int(rng.integers(4))
    u = float(rng.uniform(0.1, 0.9))
    start = [(u * w, -radius), (u * w, h + radius), (-radius, u * h), (w + radius, u * h)][side]
    aim = np.array([rng.uniform(0.25, 0.75) * w, rng.uniform(0.25, 0.75) * h])
    heading = (aim - start) / np.linalg.norm(aim - start)
    speed = float(rng.uniform(0.05, 0.3))
    enter = int(rng.integers(0, 60))
    crossing = (np.hypot(w, h) + 2 * radius) / speed / sc.dynamics.dt
    return Intruder(radius, start, tuple(speed * heading), enter, enter + int(np.ceil(crossing)))


def _box(rng: np.random.Generator, sc: Scenario, radius: float) -> Intruder | None:
    """Somewhere clear of every start and target slot by 2 cm, and of the object; None after 50 tries."""
    w, h = sc.arena
    slots = np.concatenate([sc.starts, sc.targets])
    lo, hi = sc.polygon.min(0), sc.polygon.max(0)
    for _ in range(50):
        centre = np.array([rng.uniform(radius, w - radius), rng.uniform(radius, h - radius)])
        clear_of_slots = np.linalg.norm(slots - centre, axis=1).min() > radius + sc.robot_radius + 0.02
        clear_of_object = ((centre < lo - radius) | (centre > hi + radius)).any()
        if clear_of_slots and clear_of_object:
            return Intruder(radius, tuple(centre))
    return None


def random_intruders(rng: np.random.Generator, sc: Scenario) -> list[Intruder]:
    """One to three intruders, each a walker (two in three) or a box (module docstring)."""
    out = []
    for _ in range(int(rng.integers(1, 4))):
        radius = float(rng.uniform(0.03, 0.08))
        intruder = _walker(rng, sc, radius) if rng.random() < 2 / 3 else _box(rng, sc, radius)
        if intruder is not None:
            out.append(intruder)
    return out


def intruder_episode(task: tuple[str, int, str | None, StackConfig]) -> dict:
    """One seed of a link condition with random intruders, the stack and bare."""
    name, seed, policy, stack_config = task
    out = {"condition": name, "seed": seed, "policy": policy or "scripted"}

    def with_intruders(world, seed: int) -> IntruderFleet:
        return IntruderFleet(world, random_intruders(np.random.default_rng([seed, 1]), world.scenario),
                             SIGHTING_DELAY_TICKS)

    for key, fleet, m in paired_task_runs(name, seed, policy, stack_config, with_intruders):
        near = fleet.watch.summary()
        out[f"success_{key}"], out[f"collided_{key}"] = m.success, m.collided
        out[f"drove_in_{key}"] = near["drive_in_ticks"] > 0
        out[f"min_gap_mm_{key}"] = near["min_gap_mm"]
        out[f"drive_in_speed_{key}"] = near["max_drive_in_speed"]
    return out


def run_intruders(names: list[str], episodes: int, workers: int, seed: int, policy: str | None,
                  stack: StackConfig | None = None) -> dict:
    """The ``intruders`` document: per condition and controller (module docstring)."""
    stack = stack or StackConfig()
    unknown = [nm for nm in names if nm not in CONDITIONS]
    if unknown:
        raise ValueError(f"unknown condition(s) {unknown}; choose from {','.join(CONDITIONS)}")
    sources = [None] + ([policy] if policy is not None else [])
    rows = map_episodes(intruder_episode, [(nm, seed + k, src, stack) for nm in names for k in range(episodes)
                                           for src in sources], workers, "intruders")
    doc: dict = {}
    for nm in names:
        for src in sources:
            got = [r for r in rows if r["condition"] == nm and r["policy"] == (src or "scripted")]
            doc.setdefault(nm, {})["scripted" if src is None else "policy"] = _summary(got)
    return doc


def _summary(rows: list[dict]) -> dict:
    def gaps(key: str) -> list[float]:
        return [r[f"min_gap_mm_{key}"] for r in rows if r[f"min_gap_mm_{key}"] is not None]

    on, off = gaps("on"), gaps("off")
    return {"episodes": len(rows), "sighting_delay_ticks": SIGHTING_DELAY_TICKS,
            "drive_in_episodes": sum(r["drove_in_on"] for r in rows),
            "drive_in_episodes_bare": sum(r["drove_in_off"] for r in rows),
            "contact_episodes": sum(r["collided_on"] for r in rows),
            "contact_episodes_bare": sum(r["collided_off"] for r in rows),
            "success": float(np.mean([r["success_on"] for r in rows])),
            "success_bare": float(np.mean([r["success_off"] for r in rows])),
            "success_clear": float(np.mean([r["success_on"] and not r["drove_in_on"] for r in rows])),
            "success_clear_bare": float(np.mean([r["success_off"] and not r["drove_in_off"] for r in rows])),
            "max_drive_in_speed": max(r["drive_in_speed_on"] for r in rows),
            "max_drive_in_speed_bare": max(r["drive_in_speed_off"] for r in rows),
            "min_gap_mm": min(on) if on else None, "min_gap_mm_bare": min(off) if off else None,
            "median_min_gap_mm": float(np.median(on)) if on else None,
            "median_min_gap_mm_bare": float(np.median(off)) if off else None}
