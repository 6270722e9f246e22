"""Env-steps per second of the batched formation env against VMAS, measured in one run on the CPU.

One call of ``step`` on E environments counts as E env-steps. For every robot count N and env count
E the script times ``sim.batched_env.BatchedFormationEnv`` (scenario ``transport-N``; its default
reward, ``formation``, and the trainer's, ``formation-training-reward``, which solves the
robot-target assignment every step: enumeration for N <= 4, scipy above) and the VMAS 1.5.2
scenarios ``transport`` and ``navigation`` with ``n_agents = N`` and ``num_envs = E``.

Fairness (the same for every simulator):

* CPU, the same torch thread count (``--threads``, default 1), gradients off.
* Random actions uniform in each simulator's action space: ours (E, N, 2) in [-1, 1] m/s^2 per
  axis; VMAS one (E, 2) tensor per agent from ``env.get_random_action`` (uniform in ``u_range``).
  A bank of 8 action sets is drawn before timing and cycled, so random-number generation is not
  timed.
* Each step returns observations: ours the entity tokens (E, N, 2N+1, 4) with their mask, reward
  (E, N) and done (E,); VMAS a list of N observation tensors, rewards, dones and infos.
* Episode ends: ours restarts finished environments inside ``step`` (every 128 steps), and that
  cost is in the timing; VMAS runs without a step limit and is not reset (random actions
  practically never finish its episodes), so its numbers carry no reset cost.
* ``--warmup`` untimed steps, then ``--repeats`` timed runs of ``--steps`` steps; the median
  rate of the repeats is reported. For each (robots, envs) pair the simulators' repeats are
  interleaved, so a change of machine load hits all of them alike and the ratios stay fair.

Output: a table (sim, robots, envs, steps/s, ratio vs vmas-transport at the same robots and envs)
or, with ``--json``, ``{"rows": [{"sim", "robots", "envs", "steps_per_s"}, ...], ...}`` on stdout.
Progress goes to stderr. Without VMAS the script stops with exit code 2 unless ``--no-peer``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

_BENCH_DIR = Path(__file__).resolve().parent
for _path in (_BENCH_DIR, _BENCH_DIR.parent):
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))

import torch  # noqa: E402
from _common import (  # noqa: E402
    add_output_args,
    add_seed_arg,
    format_rate,
    median_rates,
    positive_int,
    positive_int_list,
    print_json,
    print_table,
    progress,
    robot_count_list,
    set_threads,
)

from sim.batched_env import BatchedFormationEnv  # noqa: E402
from sim.scenario import MAX_ROBOTS, transport_scenario  # noqa: E402

FORMATION = "formation"
FORMATION_TRAINING = "formation-training-reward"
VMAS_SCENARIOS = {"vmas-transport": "transport", "vmas-navigation": "navigation"}
REFERENCE = "vmas-transport"
VMAS_VERSION = "1.5.2"
ACTION_BANK = 8
INSTALL_HINT = ("install it with `pip install -c constraints.txt -e '.[bench]'` "
                f"(vmas=={VMAS_VERSION}), or pass --no-peer to measure the formation env alone")


class PeerMissingError(RuntimeError):
    """VMAS, the peer simulator, cannot be imported."""


def import_vmas() -> Any:
    """The ``vmas`` module, or :class:`PeerMissingError` naming the fix."""
    try:
        import vmas
    except ImportError as exc:
        raise PeerMissingError(f"vmas is not importable ({exc}); {INSTALL_HINT}") from exc
    return vmas


def formation_stepper(robots: int, envs: int, seed: int, training_reward: bool = False) -> Callable[[int], Any]:
    """``step(k)``: one step of ``envs`` formation envs with the k-th (cycled) random action set;
    ``training_reward``: the trainer's reward (``MAPPOConfig`` default), which solves the
    robot-target assignment every step."""
    from controllers.mappo.config import MAPPOConfig
    from sim.reward import RewardWeights

    weights = MAPPOConfig().build_reward_weights() if training_reward else RewardWeights()
    env = BatchedFormationEnv(transport_scenario(robots), envs, seed=seed, reward_weights=weights)
    env.reset()
    gen = torch.Generator().manual_seed(seed)
    bank = [torch.rand(envs, robots, 2, generator=gen) * 2 - 1 for _ in range(ACTION_BANK)]

    def step(k: int) -> Any:
        return env.step(bank[k % ACTION_BANK])

    return step


def vmas_stepper(vmas: Any, scenario: str, robots: int, envs: int, seed: int) -> Callable[[int], Any]:
    """``step(k)``: one step of ``envs`` VMAS envs of ``scenario`` with ``robots`` agents."""
    env = vmas.make_env(scenario, num_envs=envs, device="cpu", continuous_actions=True,
                        seed=seed, n_agents=robots)
    if len(env.agents) != robots:
        raise RuntimeError(f"VMAS {scenario!r} made {len(env.agents)} agents, asked for {robots}")
    env.reset()
    bank = [[env.get_random_action(agent) for agent in env.agents] for _ in range(ACTION_BANK)]

    def step(k: int) -> Any:
        return env.step(bank[k % ACTION_BANK])

    return step


def run_benchmark(envs: Sequence[int], robots: Sequence[int], *, steps: int, repeats: int,
                  warmup: int, peer: bool, seed: int = 0) -> list[dict[str, Any]]:
    """Measure every (robots, envs) pair; rows ``{"sim", "robots", "envs", "steps_per_s"}``.

    With ``peer`` the VMAS scenarios are measured beside the formation env of the same pair, their
    timed repeats interleaved with its repeats (see :func:`_common.median_rates`).
    """
    for n in robots:
        if not 1 <= n <= MAX_ROBOTS:
            raise ValueError(f"--robots values must be in 1..{MAX_ROBOTS}, got {n}")
    vmas = import_vmas() if peer else None
    sims = [FORMATION, FORMATION_TRAINING] + (list(VMAS_SCENARIOS) if peer else [])
    rows: list[dict[str, Any]] = []
    for n in robots:
        for e in envs:
            progress(f"  robots={n:<3} envs={e:<6} {', '.join(sims)} ...")
            steppers = {FORMATION: formation_stepper(n, e, seed),
                        FORMATION_TRAINING: formation_stepper(n, e, seed, training_reward=True)}
            for sim in sims[2:]:
                steppers[sim] = vmas_stepper(vmas, VMAS_SCENARIOS[sim], n, e, seed)
            rates = median_rates(steppers, steps=steps, repeats=repeats, warmup=warmup,
                                 items_per_call=e)
            del steppers
            for sim in sims:
                rows.append({"sim": sim, "robots": n, "envs": e, "steps_per_s": rates[sim]})
            progress("    " + ", ".join(f"{sim} {format_rate(rates[sim])}" for sim in sims)
                     + " env-steps/s")
    return rows


def ratio_vs_reference(rows: Sequence[dict[str, Any]]) -> list[float | None]:
    """For each row, its rate divided by ``vmas-transport``'s at the same robots and envs."""
    ref = {(r["robots"], r["envs"]): r["steps_per_s"] for r in rows if r["sim"] == REFERENCE}
    out: list[float | None] = []
    for r in rows:
        base = ref.get((r["robots"], r["envs"]))
        out.append(r["steps_per_s"] / base if base else None)
    return out


def table_rows(rows: Sequence[dict[str, Any]]) -> list[list[str]]:
    ratios = ratio_vs_reference(rows)
    return [[r["sim"], str(r["robots"]), str(r["envs"]), format_rate(r["steps_per_s"]),
             "-" if q is None else f"{q:.2f}x"] for r, q in zip(rows, ratios, strict=True)]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sim_throughput.py",
        allow_abbrev=False,
        description=__doc__.split("\n\n")[0],
        epilog="\n\n".join(__doc__.split("\n\n")[1:]),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--envs", type=positive_int_list, default=[1, 64, 1024, 4096],
                        help="comma-separated numbers of parallel environments (default: 1,64,1024,4096)")
    parser.add_argument("--robots", type=robot_count_list, default=[3, 5],
                        help=f"comma-separated robot (agent) counts, 1..{MAX_ROBOTS} (default: 3,5)")
    parser.add_argument("--steps", type=positive_int, default=256,
                        help="timed steps per repeat (default: 256, two formation episodes)")
    parser.add_argument("--repeats", type=positive_int, default=3,
                        help="timed repeats; the median is reported (default: 3)")
    parser.add_argument("--warmup", type=int, default=10,
                        help="untimed steps before the repeats (default: 10)")
    add_seed_arg(parser, "every simulator")
    parser.add_argument("--peer", action=argparse.BooleanOptionalAction, default=True,
                        help="also measure the VMAS scenarios, the peer (default on; --no-peer: "
                             "the formation env alone, no VMAS needed, no ratio column)")
    add_output_args(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.warmup < 0:
        parser.error(f"--warmup must be >= 0, got {args.warmup}")
    peer = args.peer
    vmas_version = None
    if peer:
        try:
            vmas_version = getattr(import_vmas(), "__version__", "unknown")
        except PeerMissingError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if vmas_version != VMAS_VERSION:
            progress(f"warning: vmas {vmas_version} installed; the comparison is defined for "
                     f"vmas=={VMAS_VERSION}")
    threads = set_threads(args.threads)
    progress(f"torch {torch.__version__}, CPU, torch threads = {threads}, vmas = {vmas_version}, "
             f"steps = {args.steps}, repeats = {args.repeats}, warmup = {args.warmup}")
    rows = run_benchmark(args.envs, args.robots, steps=args.steps, repeats=args.repeats,
                         warmup=args.warmup, peer=peer, seed=args.seed)
    if args.json:
        print_json({"rows": rows, "torch_threads": threads, "torch": torch.__version__,
                    "vmas": vmas_version, "device": "cpu", "steps": args.steps,
                    "repeats": args.repeats, "warmup": args.warmup})
    else:
        print(f"env-steps/s on the CPU, torch threads = {threads}, median of {args.repeats} "
              f"x {args.steps} steps")
        print_table(["sim", "robots", "envs", "steps/s", "vs vmas-transport"], table_rows(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
