"""The exported typed actor's graph (``deploy/export/graph.py``) against the actor's own graph.

Both are the same contract (:class:`deploy.export.contract.PolicyContract`) around the same
untrained typed actor, written to ONNX and run by ONNX Runtime with the control path's options
(:func:`deploy.robot.onnx_session`, one thread): ``actor`` computes the actor's own ``rows``
(what an export without the rewrite holds), ``rows`` the rewritten graph the files hold. For
each: graph nodes, model size, the largest difference from the eager actor over the export
check's fleets (N = 1..21, batch 1 and 16, with and without masked tokens), the ONNX call alone
(p50/p99 over interleaved rounds on one fleet's tokens) and the whole 5-robot control tick with
each (``bench/safety.py``'s episodes, stacks taking turns), with its policy stage.

Output: a table, or with ``--json`` one document ``{"robots": N, "ticks": T, "graphs": {"actor":
{"nodes", "bytes", "max_abs_diff", "call_ms": {"p50", "p99"}, "tick_ms": {"p50", "p99"},
"policy_stage_ms": {"p50", "p99"}}, "rows": {...}}, "speedup_p50": {"call", "policy_stage",
"tick"}}`` (speed-ups: actor / rows).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

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
from bench.safety import _random_actor, _tick_latency  # noqa: E402
from deploy.export import VERIFY_COUNTS, ExportedPolicy, compare, random_fleet_rows  # noqa: E402
from deploy.export.contract import PolicyContract  # noqa: E402
from deploy.export.formats import BoundRunner, onnx_model  # noqa: E402
from deploy.robot import onnx_session  # noqa: E402
from sim.scenario import MAX_ROBOTS, make_scenario, transport_scenario  # noqa: E402


def graphs(seed: int) -> tuple[PolicyContract, dict[str, tuple[int, int, BoundRunner]]]:
    """The eager reference and, per graph, ``(nodes, bytes, runner)``."""
    actor = _random_actor(seed)
    reference = PolicyContract(actor).eval()
    out = {}
    for name, contract in (("actor", reference), ("rows", PolicyContract.for_export(actor).eval())):
        proto = onnx_model(contract, None)
        data = proto.SerializeToString()
        out[name] = (len(proto.graph.node), len(data), BoundRunner(onnx_session(data)))
    return reference, out


def call_times(runners: dict[str, BoundRunner], n: int, rounds: int, calls: int, seed: int) -> dict[str, np.ndarray]:
    """Per runner, the ONNX call's times [ms] on one fleet's tokens, in interleaved rounds."""
    tokens, mask = random_fleet_rows(n, 1, torch.Generator().manual_seed(seed), make_scenario("paper-5"))
    tokens, mask = tokens.numpy(), mask.numpy()
    samples = {name: [] for name in runners}
    for _ in range(rounds):
        for name, run in runners.items():
            for _ in range(calls // 4):
                run(tokens, mask)
            for _ in range(calls):
                t0 = time.perf_counter_ns()
                run(tokens, mask)
                samples[name].append(time.perf_counter_ns() - t0)
    return {name: np.asarray(v) / 1e6 for name, v in samples.items()}


def measure(n: int, ticks: int, warmup: int, seed: int) -> dict:
    reference, built = graphs(seed)
    runners = {name: runner for name, (_, _, runner) in built.items()}
    calls = call_times(runners, n, rounds=20, calls=max(ticks // 20, 10), seed=seed)
    meta = {"file_format": "onnx", "accel_limit": reference.accel_limit, "robot_counts": list(range(1, MAX_ROBOTS + 1)),
            "variant": "TypedSDPAActor"}
    policies = {name: ExportedPolicy(Path(f"{name}.onnx"), runner, meta) for name, runner in runners.items()}
    ticked = _tick_latency(transport_scenario(n), policies, ticks, warmup, seed, "fused")
    doc: dict = {"robots": n, "ticks": ticks, "graphs": {}}
    for name, (nodes, size, runner) in built.items():
        worst, _ = compare(runner, reference, VERIFY_COUNTS, make_scenario("paper-5"), seed=seed + 1)
        row = ticked[name]
        doc["graphs"][name] = {
            "nodes": nodes, "bytes": size, "max_abs_diff": worst,
            "call_ms": p50_p99(calls[name]),
            "tick_ms": {"p50": row["p50"], "p99": row["p99"]},
            "policy_stage_ms": {"p50": row["policy_stage_p50"], "p99": row["policy_stage_p99"]}}
    g = doc["graphs"]
    doc["speedup_p50"] = {key: g["actor"][f"{key}_ms"]["p50"] / g["rows"][f"{key}_ms"]["p50"]
                          for key in ("call", "policy_stage", "tick")}
    return doc


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_tick_args(parser, "graph")
    add_output_args(parser)
    args = parser.parse_args(argv)
    set_threads(args.threads)
    progress(f"export graph: {args.robots} robots, {args.ticks} ticks per graph")
    doc = measure(args.robots, args.ticks, args.warmup, args.seed)
    if args.json:
        print_json(doc)
        return 0
    rows = [[name, g["nodes"], f"{g['bytes'] / 1e3:.0f}", f"{g['max_abs_diff']:.1e}",
             f"{g['call_ms']['p50']:.3f} / {g['call_ms']['p99']:.3f}",
             f"{g['policy_stage_ms']['p50']:.3f} / {g['policy_stage_ms']['p99']:.3f}",
             f"{g['tick_ms']['p50']:.3f} / {g['tick_ms']['p99']:.3f}"] for name, g in doc["graphs"].items()]
    print_table(["graph", "nodes", "kB", "vs actor", "ONNX call p50 / p99 [ms]", "policy stage", "tick"], rows)
    s = doc["speedup_p50"]
    print(f"actor / rows, p50: call {s['call']:.2f}x, policy stage {s['policy_stage']:.2f}x, tick {s['tick']:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
