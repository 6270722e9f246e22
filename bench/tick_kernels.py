"""The control tick with its compiled kernels against the same tick in its numpy formulation.

Two ControlStacks with the defaults (safety filter, latency prediction, MEC, position estimator,
docking) run the same exported ONNX policy (an untrained typed actor) on the same states, taken
from scripted-controller episodes in pymunk with model error, one episode each in turn. One
uses the compiled stages (:mod:`controllers.jit`); in the other every compiled stage is swapped
for the numpy formulation the tests hold it equal to bit for bit (``tests/controllers/*_reference.py``:
compensator, latency prediction, position estimator, docking, barrier rows and sweep, tokens),
so their commands are identical and only the time differs. The row checks between the stages
(:mod:`controllers.array_kernels`, the filter's ``screen``, the re-check's first test, the late
test and the command history) stay compiled in both: their parity tests hold them to the numpy
lines they replaced, so the "numpy" tick here is faster than the tick before them. Reported per
stage: observe (estimators, tokens), policy (the ONNX call), safety (docking, prediction,
filter), mec (compensation, re-check) and the whole tick, p50/p99 [ms], and the ratio numpy /
compiled.

Output: a table, or with ``--json`` one document ``{"robots": N, "ticks": T, "compiled":
{"total": {"p50", "p99"}, "observe": ..., "policy": ..., "safety": ..., "mec": ...}, "numpy":
{...}, "speedup_p50": {"total": ..., ...}, "identical_commands": bool}``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench._common import (  # noqa: E402
    add_output_args,
    add_tick_args,
    p50_p99,
    print_json,
    print_table,
    progress,
    set_threads,
)
from bench.safety import MEC_ERROR, _random_actor  # noqa: E402
from controllers.scripted import ScriptedController  # noqa: E402
from deploy.export import export_policy, load_exported  # noqa: E402
from sim.observations import fleet_tokens_np  # noqa: E402
from sim.pymunk_world import PymunkWorld  # noqa: E402
from sim.scenario import transport_scenario  # noqa: E402
from stack.pipeline import ControlStack  # noqa: E402
from tests.controllers.docking_reference import NumpyDocking  # noqa: E402
from tests.controllers.mec_reference import NumpyMec  # noqa: E402
from tests.controllers.position_estimator_reference import NumpyPositionEstimator  # noqa: E402
from tests.controllers.safety.fused_reference import NumpyFusedScene  # noqa: E402
from tests.controllers.safety.latency_reference import NumpyPredictor  # noqa: E402

STAGES = ("total", "observe", "policy", "safety", "mec")


def numpy_stack(stack: ControlStack, n: int) -> ControlStack:
    """``stack`` with every compiled stage replaced by its numpy formulation (for N robots); the
    row checks between the stages stay compiled (module docstring)."""
    dyn, cfg = stack.dynamics, stack.config
    stack.mec = NumpyMec(dyn, cfg.mec_config)
    stack.predictor = NumpyPredictor(dyn, cfg.latency)
    stack.positions = NumpyPositionEstimator(dyn.dt)
    stack.docking = NumpyDocking(stack.scenario.robot_radius, dyn.accel_limit, cfg.docking)
    problem = stack.safety.problem(n)
    old = problem.fused
    problem.fused = NumpyFusedScene(old.radius, old.arena, old.dynamics, old.config, old.n, old.pieces)

    def numpy_tokens(self, state):
        array, tensor, mask = self._buffers[state.num_robots]
        fleet_tokens_np(state.positions, state.velocities, state.targets, self._polygon, self.scenario.arena, array)
        return tensor, mask

    stack._network_input = types.MethodType(numpy_tokens, stack)
    return stack


def record_states(n: int, ticks: int, seed: int) -> list[list]:
    """Scripted-controller episodes in pymunk with model error, ``ticks`` states in all."""
    scenario, episodes, total = transport_scenario(n), [], 0
    world = PymunkWorld(scenario, MEC_ERROR)
    while total < ticks:
        state, ctl, states = world.reset(seed=seed + len(episodes)), ScriptedController(scenario), []
        for _ in range(min(scenario.dynamics.episode_steps, ticks - total)):
            states.append(state)
            world.send_accelerations(ctl(state))
            state = world.step()
        episodes.append(states)
        total += len(states)
    return episodes


def measure(n: int, ticks: int, warmup: int, seed: int) -> dict:
    scenario = transport_scenario(n)
    with tempfile.TemporaryDirectory() as tmp:
        reports = export_policy(_random_actor(seed), Path(tmp) / "policy", dt=0.05, trained_robots=3,
                                formats=("onnx",))
        policy = load_exported(reports[0].path)
    stacks = {"compiled": ControlStack(scenario, policy), "numpy": ControlStack(scenario, policy)}
    stacks["compiled"].tick(record_states(n, 1, seed)[0][0])      # the per-N buffers exist
    stacks["numpy"].tick(record_states(n, 1, seed)[0][0])
    numpy_stack(stacks["numpy"], n)
    episodes = record_states(n, warmup + ticks, seed)
    samples = {name: {stage: [] for stage in STAGES} for name in stacks}
    identical, seen, order = True, 0, list(stacks)
    for states in episodes:
        order = order[1:] + order[:1]
        commands = {}
        for name in order:
            stacks[name].reset()
            commands[name] = []
            for k, state in enumerate(states):
                tick = stacks[name].tick(state)
                commands[name].append(tick.a_cmd)
                if seen + k >= warmup:
                    for stage in STAGES:
                        samples[name][stage].append(tick.timings_ns[stage] / 1e6)
        identical &= all(np.array_equal(a, b) for a, b in zip(commands["compiled"], commands["numpy"], strict=True))
        seen += len(states)
    out = {"robots": n, "ticks": ticks, "identical_commands": bool(identical)}
    for name, by_stage in samples.items():
        out[name] = {stage: p50_p99(v) for stage, v in by_stage.items()}
    out["speedup_p50"] = {stage: out["numpy"][stage]["p50"] / out["compiled"][stage]["p50"] for stage in STAGES}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_tick_args(parser, "stack")
    add_output_args(parser)
    args = parser.parse_args(argv)
    set_threads(args.threads)
    progress(f"tick kernels: {args.robots} robots, {args.ticks} ticks per stack")
    result = measure(args.robots, args.ticks, args.warmup, args.seed)
    if args.json:
        print_json(result)
        return 0
    rows = [[stage, f"{result['compiled'][stage]['p50']:.3f}", f"{result['compiled'][stage]['p99']:.3f}",
             f"{result['numpy'][stage]['p50']:.3f}", f"{result['numpy'][stage]['p99']:.3f}",
             f"{result['speedup_p50'][stage]:.2f}x"] for stage in STAGES]
    print_table(["stage", "compiled p50 [ms]", "p99", "numpy p50 [ms]", "p99", "numpy / compiled"], rows)
    print(f"identical commands: {result['identical_commands']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
