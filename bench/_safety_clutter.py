"""Part (f) of bench/safety.py: a tick with a cluttered arena, every disc in the QP or only those
that can bind (:mod:`controllers.safety.relevance`).

A tracker reports ``K`` boxes of radius 1-3 cm anywhere in the 1 x 1 arena
(:func:`sim.intruders.scattered_boxes`). The scripted controller drives paper-5 in pymunk with two ticks of command delay
through the default stack (only the binding discs reach the QP); on each state a second stack
whose filter takes every disc (``StackConfig(all_tracker_discs=True)``, the peer) runs the same
tick, the two taking turns to go first. Per K: tick p50/p99 of both [ms], the p50 ratio, the
largest number of discs the pruned filter took, the ticks each filter answered with its slack QP because OSQP failed (on the large
problem OSQP runs out of iterations), and the largest difference between the two stacks'
commands [m/s^2] over the ticks before their first disagreement (another status, or commands
``AGREE`` apart: OSQP's tolerance) in each episode: from there each stack predicts from its own
commands, and only the pruned stack's reach the robots, so later ticks compare different pasts.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from tqdm import tqdm

from controllers.scripted import ScriptedController
from sim.intruders import scattered_boxes
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import make_scenario
from stack.pipeline import ControlStack, StackConfig

SCENARIO = "paper-5"
AGREE = 1e-5   # [m/s^2]


def run_clutter(counts: list[int], episodes: int, ticks: int, seed: int) -> dict:
    """``{"K": {"discs", "ticks", "p50_ms", "p99_ms", "p50_ms_all", "p99_ms_all", "speedup_p50",
    "max_discs_in_qp", "slack_ticks", "slack_ticks_all", "compared_ticks", "max_command_diff"}}``
    over ``episodes`` episodes of ``ticks`` ticks."""
    sc = make_scenario(SCENARIO)
    out = {}
    for count in counts:
        times = {"pruned": [], "all": []}
        worst, most, compared = 0.0, 0, 0
        slack = {"pruned": 0, "all": 0}
        for e in tqdm(range(episodes), desc=f"clutter K={count}", unit="episode", file=sys.stderr, leave=False):
            rng = np.random.default_rng(seed + e)
            boxes = scattered_boxes(rng, sc.starts, sc.arena, sc.robot_radius, count) if count else None
            world = PymunkWorld(sc, ModelError(delay_ticks=2))
            state = world.reset(seed=seed + e)
            stacks = {"pruned": ControlStack(sc, ScriptedController(sc), StackConfig()),
                      "all": ControlStack(sc, ScriptedController(sc), StackConfig(all_tracker_discs=True))}
            rows: list[int] = []
            stacks["pruned"].safety.filter = _counting(stacks["pruned"].safety.filter, rows)
            exact, order = True, list(stacks)
            for _ in range(ticks):
                tick = {}
                order = order[1:] + order[:1]      # going first costs 10-15 %: each goes first in turn
                for name in order:
                    start = time.perf_counter()
                    tick[name] = stacks[name].tick(state.replaced(obstacles=boxes))
                    times[name].append(time.perf_counter() - start)
                    slack[name] += tick[name].infeasible
                diff = float(np.abs(tick["pruned"].a_cmd - tick["all"].a_cmd).max())
                exact = exact and tick["pruned"].safety_status == tick["all"].safety_status and diff <= AGREE
                if exact:
                    compared += 1
                    worst = max(worst, diff)
                world.send_accelerations(tick["pruned"].a_cmd)
                state = world.step()
            most = max(most, max(rows, default=sc.num_robots) - sc.num_robots)
        ms = {name: 1e3 * np.asarray(t) for name, t in times.items()}
        out[str(count)] = {"discs": count, "ticks": len(ms["pruned"]),
                           "p50_ms": float(np.percentile(ms["pruned"], 50)),
                           "p99_ms": float(np.percentile(ms["pruned"], 99)),
                           "p50_ms_all": float(np.percentile(ms["all"], 50)),
                           "p99_ms_all": float(np.percentile(ms["all"], 99)),
                           "speedup_p50": float(np.percentile(ms["all"], 50) / np.percentile(ms["pruned"], 50)),
                           "max_discs_in_qp": int(most), "slack_ticks": slack["pruned"],
                           "slack_ticks_all": slack["all"], "compared_ticks": compared, "max_command_diff": worst}
    return out


def _counting(filter_call, rows: list[int]):
    """``filter_call`` that appends the number of rows it was given (robots and discs) to ``rows``."""
    def call(pos, *args, **kwargs):
        rows.append(len(pos))
        return filter_call(pos, *args, **kwargs)
    return call


def clutter_table(rows: dict) -> tuple[list[str], list[list]]:
    """Header and rows of the printed table."""
    header = ["tracker discs", "ticks", "tick p50 [ms]", "p99", "every disc in the QP: p50", "p99",
              "p50 ratio", "most discs in the QP", "slack-QP ticks", "every disc", "ticks compared",
              "largest command difference [m/s^2]"]
    return header, [[r["discs"], r["ticks"], f"{r['p50_ms']:.2f}", f"{r['p99_ms']:.2f}", f"{r['p50_ms_all']:.2f}",
                     f"{r['p99_ms_all']:.2f}", f"{r['speedup_p50']:.1f}x", r["max_discs_in_qp"], r["slack_ticks"],
                     r["slack_ticks_all"], r["compared_ticks"], f"{r['max_command_diff']:.1e}"] for r in rows.values()]


__all__ = ["clutter_table", "run_clutter"]
