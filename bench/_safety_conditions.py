"""Part (d) of bench/safety.py: the safety layer under the imperfections of a real link.

Each condition is a pymunk :class:`~sim.model_error.ModelError` (see :data:`CONDITIONS`):
none at all (``clean``, the reference); command delay of 1, 2, 3 ticks (50-150 ms); a delay
that jitters 1-3 ticks from command to command (robots acting on the newest command that
arrived; robots with a 3-tick playout buffer, ``ModelError.playout_ticks``, which turns it into
exactly 3; and robots with an adaptive one, ``ModelError.adaptive_playout``, which settles at
the largest delay seen); measurement noise (1 cm on positions, 2 cm/s on velocities); 20 % of
the states lost on the way; a robot that freezes mid-episode (silent and deaf, its own watchdog
brakes it after two ticks), and the same with a tracker over the arena that sees every robot
(``frozen_robot_tracked``: motion capture one tick late, within 5 mm and 2 cm/s, identifying
each robot, :func:`tracked`); gain 0.7 with two ticks of delay; the randomised
gain/lag/friction/disturbance model error of part (a); and an L-shaped, non-convex object in
place of the box (``bench._common.L_OBJECT``), on a clean link (``l_object``) and on one with
jittering delay, noise and dropped states at once (``l_object_link``). Per condition, on the same
seeds:

* ``episodes`` adversarial episodes (3-16 robots, the adversary of :mod:`_adversary`, random
  starts inside ``h >= 0``), once with the stack (filter + MEC: ``StackConfig()``, or its latency
  bound narrowed by ``--command-delay-ms`` as a user who knows their link would) and once bare
  (filter off, MEC off): episodes with a contact onset, ``collisions_filter_on`` /
  ``collisions_filter_off``; docking is off in both (near a free target it would take the robot
  over from the adversary, whose commands are the point);
* ``scripted`` episodes of the scripted controller on paper-3/4/5 (and of ``--policy``, if
  given): success and contact episodes with the default stack and bare, and how soon the team
  first stands on its targets (``arrival_scripted``/``arrival_policy``:
  :func:`arrival_summary`): what a filter that keeps robots safe by slowing them costs; and the
  episodes only one of the two won (``success_scripted_pairs``/``success_policy_pairs``:
  :func:`success_pairs`, with the sign test of that split); with a frozen robot, the same three
  again judged on the robots that can still be commanded (``success_{scripted,policy}_commanded``,
  ``..._commanded_bare``, ``..._commanded_pairs``: :func:`commanded_success`), beside the success
  that also asks the frozen robot to have stopped within tolerance of its target, and in how
  many episodes it did (``frozen_home_{scripted,policy}``, ``..._bare``: :func:`frozen_home`;
  a team succeeds at most that often);
* the MEC's tracking error [mm]: the scripted commands (``|a| <= 0.6``, within a 0.7-gain
  robot's reach) recorded on the nominal model, replayed open loop through the condition's world
  with the MEC on and off (filter off), against the nominal trajectory under the same delay (the
  MEC compensates model error, not latency; a frozen robot is left out): part (b) of
  bench/safety.py, per condition.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import torch
from _adversary import MAX_ROBOTS, MIN_ROBOTS, AdversarialPolicy, random_start, without_docking
from _common import L_OBJECT, map_episodes

from controllers.docking import DockingConfig
from controllers.safety import SafetyFilter
from controllers.scripted import ScriptedController
from sim.fleet import Fleet, FleetState
from sim.intruders import IntruderFleet, RobotSightings
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import Scenario, make_scenario, transport_scenario
from stack.pipeline import ControlStack, StackConfig, load_policy, nominal_step, run_episode

CONDITIONS: dict[str, dict] = {
    "clean": {},
    "delay1": {"delay_ticks": 1},
    "delay2": {"delay_ticks": 2},
    "delay3": {"delay_ticks": 3},
    "delay_jitter": {"delay_ticks": 1, "delay_jitter_ticks": 2},
    "delay_jitter_playout": {"delay_ticks": 1, "delay_jitter_ticks": 2, "playout_ticks": 3},
    "delay_jitter_adaptive": {"delay_ticks": 1, "delay_jitter_ticks": 2, "adaptive_playout": True},
    "noise": {"position_noise_std": 0.01, "velocity_noise_std": 0.02},
    "drops": {"state_drop": 0.2},
    "frozen_robot": {"freeze": "random"},
    "frozen_robot_tracked": {"freeze": "random", "tracked": True},
    "gain0.7_delay2": {"gain": 0.7, "delay_ticks": 2},
    "model": {"model": "random"},
    "l_object": {"object": "L"},
    "l_object_link": {"object": "L", "delay_ticks": 1, "delay_jitter_ticks": 2, "position_noise_std": 0.01,
                      "velocity_noise_std": 0.02, "state_drop": 0.2},
}
"""Condition name -> ModelError fields ("random": drawn per episode, see :func:`model_error`;
"tracked": a tracker over the arena also sees the robots, :func:`tracked`; "object": "L", the
scenarios' object is :data:`bench._common.L_OBJECT`, :func:`with_object`)."""

BARE = StackConfig(safety=False, mec=False)
OPEN_LOOP = StackConfig(safety=False, mec=False, docking=DockingConfig(enabled=False))
"""The replay of recorded commands: nothing but the MEC (when on) closes a loop."""
_NETWORKS: dict = {}


def model_error(name: str, rng: np.random.Generator, num_robots: int, steps: int) -> ModelError:
    """The condition's ModelError for one episode (freeze: a random robot at a random tick)."""
    fields = dict(CONDITIONS[name])
    fields.pop("tracked", None)
    fields.pop("object", None)
    if fields.get("freeze") == "random":
        fields["freeze"] = (int(rng.integers(num_robots)), int(rng.integers(5, max(6, steps // 2))))
    if fields.pop("model", None) == "random":
        angle = rng.uniform(0, 2 * np.pi)
        fields = {"gain": 0.85, "gain_spread": 0.15, "lag_tau": float(rng.uniform(0, 0.05)),
                  "floor_friction": float(rng.uniform(0, 0.1)), "disturbance_std": 0.02,
                  "disturbance": tuple(float(rng.uniform(0, 0.05)) * np.array([np.cos(angle), np.sin(angle)]))}
    return ModelError(**fields)


def with_object(name: str, scenario: Scenario) -> Scenario:
    """The scenario with the condition's object (the L inside the presets' box: their slots fit)."""
    if CONDITIONS[name].get("object") == "L":
        return dataclasses.replace(scenario, object_vertices=L_OBJECT)
    return scenario


def tracked(name: str, world: PymunkWorld, seed: int) -> Fleet:
    """The world, under a ``tracked`` condition seen by a tracker over the arena that identifies
    the robots (:class:`sim.intruders.RobotSightings` defaults: 5 mm, 2 cm/s), one tick late."""
    if not CONDITIONS[name].get("tracked"):
        return world
    return IntruderFleet(world, (), sighting_delay_ticks=1, robots=RobotSightings(seed=seed))


def _network(path: str | None):
    if path is None:
        return None
    if path not in _NETWORKS:
        _NETWORKS[path] = load_policy(path)
    return _NETWORKS[path]


def adversarial_episode(task: tuple[str, int, int, StackConfig]) -> dict:
    """One adversarial seed of a condition, the stack (filter + MEC) and bare: did each collide?"""
    name, seed, steps, stack_config = task
    torch.set_num_threads(1)
    out = {"condition": name, "seed": seed}
    for key, config in (("on", stack_config), ("off", BARE)):
        config = without_docking(config)
        rng = np.random.default_rng(seed)
        n = int(rng.integers(MIN_ROBOTS, MAX_ROBOTS + 1))
        sc = with_object(name, transport_scenario(n))
        world = tracked(name, PymunkWorld(sc, model_error(name, rng, n, steps)), seed)
        stack = ControlStack(sc, AdversarialPolicy(sc, rng), config)
        barrier = SafetyFilter(sc)
        m = run_episode(world, stack, seed, steps, start=lambda w, b=barrier, g=rng: random_start(w, b, g))
        out[f"collided_{key}"] = m.collided
        out["robots"] = n
    return out


def paired_task_runs(name: str, seed: int, policy: str | None, stack_config: StackConfig,
                     wrap: Callable[[PymunkWorld, int], Fleet] = lambda world, seed: world):
    """Episode ``seed`` of paper-3, -4 or -5 (by ``seed % 3``) under condition ``name``, run with
    the scripted controller (or ``policy``) through ``stack_config`` and bare on the same draw of
    model error; ``wrap(world, seed)`` may put the world in another fleet. Yields ("on" | "off",
    the fleet, its EpisodeMetrics)."""
    torch.set_num_threads(1)
    sc = with_object(name, make_scenario(("paper-3", "paper-4", "paper-5")[seed % 3]))
    for key, config in (("on", stack_config), ("off", BARE)):
        rng = np.random.default_rng(seed)
        world = PymunkWorld(sc, model_error(name, rng, sc.num_robots, sc.dynamics.episode_steps))
        fleet = wrap(tracked(name, world, seed), seed)
        source = _network(policy) if policy is not None else ScriptedController(sc)
        yield key, fleet, run_episode(fleet, ControlStack(sc, source, config), seed)


def task_episode(task: tuple[str, int, str | None, StackConfig]) -> dict:
    """One paper-3/4/5 episode of the scripted controller (or a policy), the stack and bare."""
    name, seed, policy, stack_config = task
    out = {"condition": name, "seed": seed, "policy": policy or "scripted"}
    for key, world, m in paired_task_runs(name, seed, policy, stack_config):
        out[f"success_{key}"], out[f"collided_{key}"] = m.success, m.collided
        out[f"arrival_{key}"] = m.arrival_step
        if world.model_error.freeze is not None:
            out[f"commanded_{key}"] = commanded_success(world, m.collided)
            out[f"frozen_home_{key}"] = frozen_home(world)
    return out


def frozen_home(world: PymunkWorld) -> bool:
    """Whether the frozen robot stopped within tolerance of some target: what a whole-team
    success needs of it, and all that the controller's work before the freeze decides (how far
    along it was); a team whose frozen robot is home fails only on what the others do."""
    true = world.true_state()
    robot = world.model_error.freeze[0]
    nearest = np.linalg.norm(true.targets - true.positions[robot], axis=1).min()
    return bool(nearest <= world.scenario.target_tolerance)


def commanded_success(world: PymunkWorld, collided: bool) -> bool:
    """Success judged on the robots a controller can still command: no contact, and every robot
    but the frozen one within tolerance of its target under the episode's assignment (the frozen
    robot, silent and deaf, stops wherever it was when it froze: where that is depends on how far
    along it was, not on anything done after)."""
    true = world.true_state()
    sigma = world.outcome().assignment[0].numpy()        # the assignment the episode was judged on
    assigned = np.linalg.norm(true.positions - true.targets[sigma], axis=1)
    keep = np.ones(len(assigned), dtype=bool)
    keep[world.model_error.freeze[0]] = False
    return bool(not collided and (assigned[keep] <= world.scenario.target_tolerance).all())


def tracking_error_mm(name: str, episodes: int, seed: int) -> dict:
    """The MEC's open-loop tracking error under the condition (module docstring) [mm]."""
    errors: dict[str, list[float]] = {"mec": [], "no_mec": []}
    for k in range(episodes):
        sc = with_object(name, make_scenario(("paper-3", "paper-4", "paper-5")[k % 3]))
        rng = np.random.default_rng(seed + k)
        me = model_error(name, rng, sc.num_robots, sc.dynamics.episode_steps)
        start = PymunkWorld(sc).reset(seed=seed + k)
        ctl = ScriptedController(dataclasses.replace(
            sc, dynamics=dataclasses.replace(sc.dynamics, accel_limit=0.6)))
        pos, vel, commands, nominal = start.positions, start.velocities, [], []
        delayed = [np.zeros_like(pos)] * me.delay_ticks
        for step in range(sc.dynamics.episode_steps):
            state = FleetState(time=step * sc.dynamics.dt, step=step, positions=pos, velocities=vel,
                               targets=start.targets, object_pose=start.object_pose)
            commands.append(ctl(state))
            delayed.append(commands[-1])
            pos, vel = nominal_step(pos, vel, delayed.pop(0), sc.dynamics)
            nominal.append(pos)
        keep = np.ones(sc.num_robots, dtype=bool)
        if me.freeze is not None:
            keep[me.freeze[0]] = False
        for key, mec in (("mec", True), ("no_mec", False)):
            world = PymunkWorld(sc, me)
            state = world.reset(seed=seed + k)
            stack = ControlStack(sc, lambda s, c=commands: c[min(s.step, len(c) - 1)],
                                 dataclasses.replace(OPEN_LOOP, mec=mec))
            dev = []
            for t in range(len(commands)):
                world.send_accelerations(stack.tick(state).a_cmd)
                state = world.step()
                dev.append(np.linalg.norm(world.true_state().positions - nominal[t], axis=1)[keep].mean())
            errors[key].append(float(np.mean(dev)))
    return {key: 1000.0 * float(np.mean(v)) for key, v in errors.items()}


def arrival_summary(rows: list[dict]) -> dict:
    """When the team first stood on its targets, default stack against bare, on the episodes
    where both arrived (paired: the same seed and model error): mean tick of each, and how
    many episodes arrived with each."""
    both = [r for r in rows if r["arrival_on"] is not None and r["arrival_off"] is not None]

    def mean(key: str) -> float | None:
        return float(np.mean([r[key] for r in both])) if both else None

    return {"paired_episodes": len(both), "mean_step": mean("arrival_on"), "mean_step_bare": mean("arrival_off"),
            "arrived": sum(r["arrival_on"] is not None for r in rows),
            "arrived_bare": sum(r["arrival_off"] is not None for r in rows)}


def success_pairs(rows: list[dict]) -> dict:
    """Success paired episode by episode (the same seed and model error): how many episodes only
    the default stack won (``stack_only``), only bare won (``bare_only``), and the two-sided sign
    test's p-value of that split (exact binomial, p = 1/2 under "neither layer differs"):
    whether a gap between the success rates is more than the draw of seeds."""
    stack_only = sum(bool(r["success_on"] and not r["success_off"]) for r in rows)
    bare_only = sum(bool(r["success_off"] and not r["success_on"]) for r in rows)
    n, k = stack_only + bare_only, min(stack_only, bare_only)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n if n else 1.0
    return {"stack_only": stack_only, "bare_only": bare_only, "sign_test_p": round(min(1.0, 2 * tail), 4)}


def run_conditions(names: list[str], episodes: int, steps: int, task_episodes: int,
                   mec_episodes: int, workers: int, seed: int, policy: str | None,
                   stack: StackConfig | None = None) -> dict:
    """The ``conditions`` document: one entry per condition (module docstring); ``stack`` is what
    the "filter + MEC" columns run (default ``StackConfig()``)."""
    stack = stack or StackConfig()
    adversarial = map_episodes(adversarial_episode, [(nm, seed + k, steps, stack) for nm in names
                                                     for k in range(episodes)], workers, "conditions: adversarial")
    sources = [None] + ([policy] if policy is not None else [])
    tasks = map_episodes(task_episode, [(nm, seed + k, src, stack) for nm in names for k in range(task_episodes)
                                        for src in sources], workers, "conditions: scripted/policy")
    doc = {}
    for nm in names:
        adv = [r for r in adversarial if r["condition"] == nm]
        entry = {"episodes": len(adv), "steps": steps, "model_error": CONDITIONS[nm],
                 "collisions_filter_on": sum(r["collided_on"] for r in adv),
                 "collisions_filter_off": sum(r["collided_off"] for r in adv),
                 "collided_seeds_filter_on": sorted(r["seed"] for r in adv if r["collided_on"])[:20]}
        for src in sources:
            rows = [r for r in tasks if r["condition"] == nm and r["policy"] == (src or "scripted")]
            tag = "scripted" if src is None else "policy"
            entry[f"{tag}_episodes"] = len(rows)
            entry[f"success_{tag}"] = float(np.mean([r["success_on"] for r in rows])) if rows else None
            entry[f"success_{tag}_bare"] = float(np.mean([r["success_off"] for r in rows])) if rows else None
            entry[f"collisions_{tag}"] = sum(r["collided_on"] for r in rows)
            entry[f"collisions_{tag}_bare"] = sum(r["collided_off"] for r in rows)
            entry[f"arrival_{tag}"] = arrival_summary(rows)
            entry[f"success_{tag}_pairs"] = success_pairs(rows)
            if rows and "commanded_on" in rows[0]:
                entry[f"success_{tag}_commanded"] = float(np.mean([r["commanded_on"] for r in rows]))
                entry[f"success_{tag}_commanded_bare"] = float(np.mean([r["commanded_off"] for r in rows]))
                entry[f"success_{tag}_commanded_pairs"] = success_pairs(
                    [{"success_on": r["commanded_on"], "success_off": r["commanded_off"]} for r in rows])
                entry[f"frozen_home_{tag}"] = sum(r["frozen_home_on"] for r in rows)
                entry[f"frozen_home_{tag}_bare"] = sum(r["frozen_home_off"] for r in rows)
        entry["tracking_error_mm"] = tracking_error_mm(nm, mec_episodes, seed)
        doc[nm] = entry
    return doc
