"""Safety layer benchmark: forward invariance in pymunk, MEC tracking error, full-tick latency.

(a) invariance: ``--episodes`` randomised pymunk episodes of ``--episode-ticks`` ticks. Each
    episode draws N in 3..16 (``transport-N``), a model error (gain 0.7..1.0 per robot, actuator lag
    0..0.05 s, floor friction 0..0.1 m/s^2, a constant disturbance up to 0.05 m/s^2 and white
    disturbance 0.02 m/s^2 per axis), random robot positions with >= 0.03 m clearance and random
    velocities scaled into the barrier's safe set ``h >= 0`` at the state and at every state the
    robots coast to over the default latency bound (3 ticks: a robot cannot brake before its
    first command arrives). Every robot keeps one adversarial
    mode: full thrust at its nearest neighbour, at the object, at the nearest wall, along a fixed
    random direction, along a fresh random direction every tick, the scripted controller, or
    (with ``--policy``) a trained policy. The ControlStack runs with the MEC on, once with the
    safety filter and once without, on the same seed, docking off (it would take a robot near a
    free target over from the adversary); an episode counts when the pymunk world records at
    least one contact onset (robot, object or wall).
(b) MEC: the scripted controller's commands, recorded on the nominal model (sim dynamics, no
    error) from each episode's start, replayed open loop through pymunk with gain 0.7, lag
    0.05 s and floor friction 0.1 m/s^2, with and without the MEC (filter off). Tracking error =
    mean over ticks and robots of |p_pymunk - p_nominal| [m].
(c) latency of ControlStack.tick (observe + policy + safety + MEC) for N robots, after warm-up,
    one torch thread, on states of scripted-controller episodes in pymunk with model error; the
    policy is ``--policy`` (a checkpoint) or an untrained typed SDPA actor, in memory as the
    default stack runs it (a typed actor by the compiled kernel of npz files,
    :class:`stack.policy_io.ModuleKernel`), and as a TorchScript module. Parts are
    reported too: observe (tokens), policy (observe + network), policy_stage (the network
    alone), safety and MEC. The same actor is then exported (``formation export``) as
    TorchScript, torch.export, ONNX and npz (the compiled kernel of :mod:`deploy.npz_policy`)
    and each file is loaded as the ControlStack loads one (``latency_ms_by_format``; ``--policy``
    an exported file: that file alone).

``--geometry`` picks the safety filter's path for (a) and (c): ``fused`` (default, the fast path
of :mod:`controllers.safety.fused`) or the reference ``fcl`` / ``analytic`` path, which gives the
same answers; run both to compare their latency.

(d) conditions: the imperfections of a real link, one by one (delay 1-3 ticks, jittering delay,
    noise, dropped states, a frozen robot, the same seen by a tracker that identifies robots,
    gain 0.7 with delay, the model error of (a), an L-shaped object on a clean and on a poor
    link), each with ``--condition-episodes``
    adversarial episodes of ``--episode-ticks`` ticks, default stack against bare, plus the
    scripted controller (and ``--policy``) and the MEC's tracking error; see
    :mod:`_safety_conditions`.
(e) intruders: ``--intruder-episodes`` paper-3/4/5 episodes per link condition of
    ``--intruder-conditions`` with one to three random walkers and boxes that a tracker reports
    two ticks late, the scripted controller (and ``--policy``) through the default stack against
    bare: episodes in which a robot drove into an intruder, contacts, success, closest approach;
    see :mod:`_safety_intruders`.
(f) clutter: tick latency with ``--clutter-discs`` boxes a tracker reports, the default stack
    (only the discs that can bind enter the QP) against one whose filter takes every disc, on
    the same states, and the largest difference of their commands; see :mod:`_safety_clutter`.

Output: a table, or with ``--json`` one document
``{"invariance": {...}, "mec": {...}, "latency_ms": {"3": {"p50", "p99", ...}, ...},
"latency_ms_torchscript_module": {"3": {...}, ...},
"latency_ms_by_format": {"torchscript": {"5": {...}}, "pt2": {...}, "onnx": {...}, "npz": {...}},
"conditions": {"delay2": {"episodes", "collisions_filter_on", "collisions_filter_off",
"success_scripted", "tracking_error_mm": {"mec", "no_mec"}, "arrival_scripted": {...}, ...}, ...},
"intruders": {"delay2": {"scripted": {"episodes", "drive_in_episodes", "drive_in_episodes_bare",
"contact_episodes", "success", "min_gap_mm", ...}, "policy": {...}}, ...},
"clutter": {"100": {"discs", "p50_ms", "p99_ms", "p50_ms_all", "p99_ms_all", "speedup_p50",
"max_discs_in_qp", "max_command_diff", ...}, ...}, "stack_config": {...}, "provenance": {...}}``: ``stack_config`` is the ``StackConfig`` the
"filter + MEC" columns of (d) ran, resolved (filter, latency and MEC settings): the default,
which covers 150 ms of command delay, unless ``--command-delay-ms`` narrows its latency bound as a
user who knows their link would (``formation eval --command-delay-ms``); (a)-(c) run the default.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
import time
from pathlib import Path

_BENCH_DIR = Path(__file__).resolve().parent
for _path in (_BENCH_DIR, _BENCH_DIR.parent):
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from _adversary import MAX_ROBOTS, MIN_ROBOTS, AdversarialPolicy, random_start, without_docking  # noqa: E402
from _common import (  # noqa: E402
    add_output_args,
    add_seed_arg,
    map_episodes,
    nonnegative_int_list,
    positive_int,
    print_json,
    print_table,
    progress,
    robot_count_list,
    set_threads,
)
from _safety_clutter import clutter_table, run_clutter  # noqa: E402
from _safety_conditions import CONDITIONS, OPEN_LOOP, run_conditions  # noqa: E402
from _safety_intruders import run_intruders  # noqa: E402
from torch import nn  # noqa: E402
from tqdm import tqdm  # noqa: E402

from controllers.safety import SafetyConfig, SafetyFilter  # noqa: E402
from controllers.scripted import ScriptedController  # noqa: E402
from sim.fleet import FleetState  # noqa: E402
from sim.pymunk_world import ModelError, PymunkWorld  # noqa: E402
from sim.scenario import make_scenario, transport_scenario  # noqa: E402
from stack.commands import argtypes  # noqa: E402
from stack.commands.latency_args import add_command_delay_arg, latency_config  # noqa: E402
from stack.pipeline import ControlStack, StackConfig, load_policy, nominal_step, run_episode  # noqa: E402

MEC_ERROR = ModelError(gain=0.7, lag_tau=0.05, floor_friction=0.1)
MEC_COMMAND_LIMIT = 0.6   # [m/s^2] below gain 0.7 x accel_limit 1.0: within the actuator's reach


# ------------------------------------------------------------------ (a) invariance
_NETWORK_CACHE: dict = {}


def invariance_episode(task: tuple[int, int, str | None, str]) -> dict:
    """One seed, filter on and off: contacts and the filter's counters."""
    seed, steps, policy_path, geometry = task
    torch.set_num_threads(1)
    network = None
    if policy_path is not None:
        if policy_path not in _NETWORK_CACHE:
            _NETWORK_CACHE[policy_path] = load_policy(policy_path)
        network = _NETWORK_CACHE[policy_path]
    out = {"seed": seed}
    for filt in (True, False):
        rng = np.random.default_rng(seed)
        n = int(rng.integers(MIN_ROBOTS, MAX_ROBOTS + 1))
        sc = transport_scenario(n)
        angle = rng.uniform(0, 2 * math.pi)
        me = ModelError(gain=0.85, gain_spread=0.15, lag_tau=float(rng.uniform(0, 0.05)),
                        floor_friction=float(rng.uniform(0, 0.1)),
                        disturbance=tuple(float(rng.uniform(0, 0.05)) * np.array([math.cos(angle), math.sin(angle)])),
                        disturbance_std=0.02)
        world = PymunkWorld(sc, me)
        stack = ControlStack(sc, AdversarialPolicy(sc, rng, network),
                             without_docking(StackConfig(safety=filt, mec=True,
                                                         safety_config=SafetyConfig(geometry=geometry))))
        barrier = SafetyFilter(sc, stack.config.safety_config)
        m = run_episode(world, stack, seed, steps, start=lambda w, b=barrier, g=rng: random_start(w, b, g))
        key = "on" if filt else "off"
        out["robots"] = n
        out[f"collided_{key}"] = m.collided
        if filt:
            out.update(interventions=m.interventions, infeasible=m.infeasible, fallbacks=m.fallbacks)
    return out


def run_invariance(episodes: int, steps: int, workers: int, seed: int, policy: str | None,
                   geometry: str = "fused") -> dict:
    tasks = [(seed + k, steps, policy, geometry) for k in range(episodes)]
    rows = map_episodes(invariance_episode, tasks, workers, "invariance", chunksize=4)
    on = [r["seed"] for r in rows if r["collided_on"]]
    ticks = episodes * steps
    return {"episodes": episodes, "steps": steps, "collisions_filter_on": len(on),
            "collisions_filter_off": sum(r["collided_off"] for r in rows),
            "collided_seeds_filter_on": sorted(on)[:20],
            "intervened_tick_fraction": sum(r["interventions"] for r in rows) / ticks,
            "infeasible_tick_fraction": sum(r["infeasible"] for r in rows) / ticks,
            "fallback_tick_fraction": sum(r["fallbacks"] for r in rows) / ticks,
            "robots": [MIN_ROBOTS, MAX_ROBOTS], "policy": policy or "adversarial+scripted",
            "geometry": geometry}


# ------------------------------------------------------------------------ (b) MEC
class Replay:
    """Callable policy replaying a recorded (T, N, 2) command sequence by tick index."""

    def __init__(self, commands: np.ndarray):
        self.commands = commands

    def __call__(self, state: FleetState) -> np.ndarray:
        return self.commands[min(state.step, len(self.commands) - 1)]


def mec_tracking(episodes: int, seed: int, command_limit: float = MEC_COMMAND_LIMIT) -> dict:
    """Open-loop tracking error of the nominal trajectory (module docstring, part (b)).

    ``command_limit`` [m/s^2] caps the recorded commands: a robot with gain g can realise a
    command a only if a / g <= accel_limit, so the MEC can only compensate below g * accel_limit.
    """
    errors = {"without": [], "with": []}
    for k in tqdm(range(episodes), desc=f"mec (|a| <= {command_limit})", unit="ep", file=sys.stderr):
        sc = make_scenario(("paper-3", "paper-4", "paper-5")[k % 3])
        start = PymunkWorld(sc).reset(seed=seed + k)
        ctl = ScriptedController(dataclasses.replace(
            sc, dynamics=dataclasses.replace(sc.dynamics, accel_limit=command_limit)))
        pos, vel, nominal, commands = start.positions, start.velocities, [], []
        for step in range(sc.dynamics.episode_steps):
            state = FleetState(time=step * sc.dynamics.dt, step=step, positions=pos, velocities=vel,
                               targets=start.targets, object_pose=start.object_pose)
            commands.append(ctl(state))
            pos, vel = nominal_step(pos, vel, commands[-1], sc.dynamics)
            nominal.append(pos)
        nominal = np.array(nominal)
        for key, mec in (("without", False), ("with", True)):
            world = PymunkWorld(sc, MEC_ERROR)
            state = world.reset(seed=seed + k)
            stack = ControlStack(sc, Replay(np.array(commands)), dataclasses.replace(OPEN_LOOP, mec=mec))
            deviation = []
            for t in range(len(commands)):
                world.send_accelerations(stack.tick(state).a_cmd)
                state = world.step()
                deviation.append(np.linalg.norm(world.true_state().positions - nominal[t], axis=1).mean())
            errors[key].append(float(np.mean(deviation)))
    without, with_mec = float(np.mean(errors["without"])), float(np.mean(errors["with"]))
    return {"tracking_error_without": without, "tracking_error_with": with_mec,
            "reduction": 1.0 - with_mec / without if without > 0 else math.nan,
            "episodes": episodes, "command_limit": command_limit,
            "model_error": {"gain": 0.7, "lag_tau": 0.05, "floor_friction": 0.1}}


# -------------------------------------------------------------------- (c) latency
def latency(robot_counts: list[int], ticks: int, warmup: int, policy: str | None, seed: int,
            geometry: str = "fused") -> tuple[dict, dict, dict]:
    """Tick latency per N: the actor in memory as the default ControlStack runs a checkpoint's
    (``latency_ms``: a typed actor by the compiled kernel, :class:`stack.policy_io.ModuleKernel`),
    the same module as TorchScript (``latency_ms_torchscript_module``), and the actor exported
    (``formation export``) as TorchScript, torch.export, ONNX and npz, each file loaded as the
    ControlStack loads one (``latency_ms_by_format``). All stacks run the same episodes in turn
    (:func:`_tick_latency`), so machine noise hits them alike. The actor: ``policy`` (a
    checkpoint; an exported file is measured alone), else a fresh typed actor."""
    from deploy.export import DEFAULT_FORMATS, ExportedPolicy, export_policy, load_exported

    loaded = load_policy(policy) if policy is not None else _random_actor(seed)
    in_memory, scripted, by_format = {}, {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        if isinstance(loaded, ExportedPolicy):
            files = {loaded.file_format: Path(policy)}
        else:
            reports = export_policy(loaded, Path(tmp) / "policy", dt=0.05, trained_robots=3)
            files = {r.meta["file_format"]: r.path for r in reports}
        networks = {name: load_exported(files[name]) for name in DEFAULT_FORMATS if name in files}
        if not isinstance(loaded, ExportedPolicy):
            networks["in_memory"], networks["in_memory_torchscript"] = loaded, torch.jit.script(loaded)
        for n in robot_counts:
            rows = _tick_latency(transport_scenario(n), networks, ticks, warmup, seed, geometry)
            if "in_memory" in rows:
                in_memory[str(n)], scripted[str(n)] = rows.pop("in_memory"), rows.pop("in_memory_torchscript")
            for name, row in rows.items():
                by_format.setdefault(name, {})[str(n)] = row
    return in_memory, scripted, by_format


def _random_actor(seed: int) -> nn.Module:
    from controllers.policy import ActorConfig, build_actor

    torch.manual_seed(seed)
    return build_actor(ActorConfig(), 3).eval()


def _tick_latency(sc, networks: dict, ticks: int, warmup: int, seed: int, geometry: str) -> dict:
    """Per network: p50/p99 [ms] of ControlStack.tick and its stages over ``ticks`` ticks after
    ``warmup``. The states come from scripted-controller episodes recorded first; every stack
    then runs each episode in turn (the order rotating per episode), as a control loop would:
    one stack at a time, on the same states."""
    config = StackConfig(safety_config=SafetyConfig(geometry=geometry))
    stacks = {name: ControlStack(sc, net, config) for name, net in networks.items()}
    episodes, total = [], 0
    world = PymunkWorld(sc, MEC_ERROR)
    while total < warmup + ticks:
        state, ctl, states = world.reset(seed=seed + len(episodes)), ScriptedController(sc), []
        for _ in range(min(sc.dynamics.episode_steps, warmup + ticks - total)):
            states.append(state)
            world.send_accelerations(ctl(state))
            state = world.step()
        episodes.append(states)
        total += len(states)
    parts = ("total", "observe", "policy", "policy_stage", "safety", "mec")
    samples = {name: {part: [] for part in parts} for name in stacks}
    intervened = dict.fromkeys(stacks, 0)
    order = list(stacks)
    seen = 0
    for states in tqdm(episodes, desc=f"latency N={sc.num_robots}", unit="episode", file=sys.stderr, leave=False):
        order = order[1:] + order[:1]
        for name in order:
            stacks[name].reset()
            for k, state in enumerate(states):
                tick = stacks[name].tick(state)
                if seen + k >= warmup:
                    t = tick.timings_ns
                    for part, value in (("total", t["total"]), ("observe", t["observe"]),
                                        ("policy", t["observe"] + t["policy"]), ("policy_stage", t["policy"]),
                                        ("safety", t["safety"]), ("mec", t["mec"])):
                        samples[name][part].append(value)
                    intervened[name] += tick.intervened
        seen += len(states)
    out = {}
    for name, by_part in samples.items():
        row = {}
        for part, values in by_part.items():
            ms = np.asarray(values) / 1e6
            prefix = "" if part == "total" else f"{part}_"
            row[f"{prefix}p50"] = float(np.percentile(ms, 50))
            row[f"{prefix}p99"] = float(np.percentile(ms, 99))
        row.update(ticks=ticks, intervened_fraction=intervened[name] / ticks, geometry=geometry)
        out[name] = row
    return out


def condition_list(text: str) -> list[str]:
    """argparse type: comma-separated names of :data:`_safety_conditions.CONDITIONS`."""
    names = [part.strip() for part in text.split(",") if part.strip()]
    unknown = [nm for nm in names if nm not in CONDITIONS]
    if not names or unknown:
        raise argparse.ArgumentTypeError(f"unknown condition(s) {unknown or text!r}; "
                                         f"choose from {','.join(CONDITIONS)}")
    return names


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=positive_int, default=1000, help="invariance episodes (default 1000)")
    parser.add_argument("--episode-ticks", type=positive_int, default=60, metavar="T",
                        help="ticks per adversarial episode of (a) and (d) (default 60)")
    argtypes.add_deprecated_alias(parser, "--steps", "--episode-ticks")
    parser.add_argument("--cpus", type=positive_int, default=2,
                        help="worker processes for (a), (d) and (e) (default 2)")
    argtypes.add_deprecated_alias(parser, "--workers", "--cpus")
    parser.add_argument("--mec-episodes", type=positive_int, default=12, help="episodes for (b) (default 12)")
    parser.add_argument("--robots", type=robot_count_list, default=[3, 5, 10, 20],
                        help="robot counts for (c) (default 3,5,10,20)")
    parser.add_argument("--ticks", type=positive_int, default=1000, help="timed ticks per N for (c) (default 1000)")
    parser.add_argument("--warmup", type=positive_int, default=100, help="untimed ticks per N for (c) (default 100)")
    parser.add_argument("--policy", default=None, help="checkpoint or TorchScript file (default: "
                        "adversarial + scripted commands in (a), an untrained actor in (c))")
    add_seed_arg(parser, "the episodes of every part")
    parser.add_argument("--geometry", choices=["fused", "fcl", "analytic"], default="fused",
                        help="safety filter path for (a) and (c): the fused fast path (default) or the "
                             "reference path on FCL or closed-form distances (same answers, slower)")
    parser.add_argument("--conditions", type=condition_list, default=list(CONDITIONS),
                        help=f"conditions for (d), comma-separated (default: all of {','.join(CONDITIONS)})")
    parser.add_argument("--condition-episodes", type=positive_int, default=300,
                        help="adversarial episodes per condition for (d) (default 300)")
    parser.add_argument("--task-episodes", type=positive_int, default=30,
                        help="scripted (and --policy) paper-3/4/5 episodes per condition for (d) (default 30)")
    parser.add_argument("--intruder-conditions", type=condition_list, default=["clean", "delay2", "noise"],
                        help="link conditions for (e), comma-separated (default clean,delay2,noise)")
    parser.add_argument("--intruder-episodes", type=positive_int, default=300,
                        help="episodes per condition and controller for (e) (default 300)")
    parser.add_argument("--clutter-discs", type=nonnegative_int_list, default=[0, 25, 100],
                        help="tracker disc counts for (f), comma-separated (default 0,25,100)")
    parser.add_argument("--clutter-episodes", type=positive_int, default=4,
                        help="paper-5 episodes of 128 ticks per disc count for (f) (default 4)")
    add_command_delay_arg(parser)
    parser.add_argument("--only", choices=["invariance", "mec", "latency", "conditions", "intruders", "clutter"],
                        default=None,
                        help="run one part only (the document then holds that key alone)")
    add_output_args(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.policy is not None and not Path(args.policy).is_file():
        print(f"error: --policy {args.policy!r} does not exist", file=sys.stderr)
        return 2
    if args.policy is not None:
        try:   # before any part runs: a stale file must not fail the run minutes in
            load_policy(args.policy)
        except Exception as exc:
            print(f"error: --policy {args.policy}: {exc}", file=sys.stderr)
            return 2
    try:
        stack_config = StackConfig(latency=latency_config(args))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    threads = set_threads(args.threads)
    start = time.perf_counter()
    doc: dict = {}
    if args.only in (None, "latency"):
        progress(f"(c) latency, N = {args.robots}, {threads} torch thread(s)")
        (doc["latency_ms"], doc["latency_ms_torchscript_module"],
         doc["latency_ms_by_format"]) = latency(args.robots, args.ticks, args.warmup, args.policy, args.seed,
                                                args.geometry)
    if args.only in (None, "mec"):
        progress("(b) MEC tracking")
        doc["mec"] = mec_tracking(args.mec_episodes, args.seed)
        doc["mec"]["saturated"] = mec_tracking(args.mec_episodes, args.seed, command_limit=1.0)
    if args.only in (None, "invariance"):
        progress(f"(a) invariance, {args.episodes} episodes x {args.episode_ticks} ticks, {args.cpus} processes")
        doc["invariance"] = run_invariance(args.episodes, args.episode_ticks, args.cpus, args.seed, args.policy,
                                           args.geometry)
    if args.only in (None, "conditions"):
        progress(f"(d) conditions {args.conditions}, {args.condition_episodes} adversarial episodes each")
        doc["conditions"] = run_conditions(args.conditions, args.condition_episodes, args.episode_ticks,
                                           args.task_episodes, args.mec_episodes, args.cpus,
                                           args.seed, args.policy, stack_config)
    if args.only in (None, "intruders"):
        progress(f"(e) intruders under {args.intruder_conditions}, {args.intruder_episodes} episodes each")
        doc["intruders"] = run_intruders(args.intruder_conditions, args.intruder_episodes, args.cpus,
                                         args.seed, args.policy, stack_config)
    if args.only in (None, "clutter"):
        progress(f"(f) clutter, {args.clutter_discs} tracker discs, {args.clutter_episodes} episodes each")
        doc["clutter"] = run_clutter(args.clutter_discs, args.clutter_episodes, 128, args.seed)
    doc.update(threads=threads, wall_s=time.perf_counter() - start,
               stack_config=dataclasses.asdict(stack_config))
    if args.json:
        print_json(doc)
    else:
        _print_tables(doc)
    return 0


def _tick(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def _print_tables(doc: dict) -> None:
    """The document of :func:`main` as one table per part it holds."""
    if "invariance" in doc:
        inv = doc["invariance"]
        print_table(["invariance", "episodes", "contact episodes, filter on", "filter off"],
                    [["pymunk, MEC on", inv["episodes"], inv["collisions_filter_on"],
                      inv["collisions_filter_off"]]])
        print()
    if "mec" in doc:
        print_table(["MEC (gain 0.7, lag, friction)", "tracking error without [m]", "with [m]", "reduction"],
                    [[f"commands <= {m['command_limit']} m/s^2", f"{m['tracking_error_without']:.4f}",
                      f"{m['tracking_error_with']:.4f}", f"{m['reduction']:.0%}"]
                     for m in (doc["mec"], doc["mec"]["saturated"])])
        print()
    if "conditions" in doc:
        print_table(["condition", "episodes", "contact, filter+MEC", "bare", "scripted success", "bare",
                     "scripted contact", "bare", "arrival tick", "bare", "tracking MEC [mm]", "no MEC"],
                    [[name, c["episodes"], c["collisions_filter_on"], c["collisions_filter_off"],
                      f"{c['success_scripted']:.2f}", f"{c['success_scripted_bare']:.2f}",
                      c["collisions_scripted"], c["collisions_scripted_bare"],
                      *(_tick(c["arrival_scripted"][k]) for k in ("mean_step", "mean_step_bare")),
                      f"{c['tracking_error_mm']['mec']:.2f}", f"{c['tracking_error_mm']['no_mec']:.2f}"]
                     for name, c in doc["conditions"].items()])
        if any("success_policy" in c for c in doc["conditions"].values()):
            print()
            print_table(["condition", "policy success, filter+MEC", "bare", "won by stack only", "bare only",
                         "sign test p", "policy contact", "bare", "arrival tick", "bare", "paired episodes"],
                        [[name, f"{c['success_policy']:.3f}", f"{c['success_policy_bare']:.3f}",
                          *(c["success_policy_pairs"][k] for k in ("stack_only", "bare_only", "sign_test_p")),
                          c["collisions_policy"], c["collisions_policy_bare"],
                          *(_tick(c["arrival_policy"][k]) for k in ("mean_step", "mean_step_bare")),
                          c["arrival_policy"]["paired_episodes"]]
                         for name, c in doc["conditions"].items()])
        commanded = [(name, tag, c) for name, c in doc["conditions"].items() for tag in ("scripted", "policy")
                     if f"success_{tag}_commanded" in c]
        if commanded:
            print()
            print_table(["condition (frozen robot left out)", "controller", "success, filter+MEC", "bare",
                         "won by stack only", "bare only", "sign test p"],
                        [[name, tag, f"{c[f'success_{tag}_commanded']:.3f}", f"{c[f'success_{tag}_commanded_bare']:.3f}",
                          *(c[f"success_{tag}_commanded_pairs"][k] for k in ("stack_only", "bare_only", "sign_test_p"))]
                         for name, tag, c in commanded])
        print()
    if "intruders" in doc:
        print_table(["condition (intruders)", "controller", "episodes", "drove in, filter+MEC", "bare",
                     "fastest [m/s]", "bare", "contact", "bare", "success", "bare", "success, none driven into",
                     "bare", "closest [mm]", "bare", "median closest", "bare"],
                    [[name, tag, r["episodes"], r["drive_in_episodes"], r["drive_in_episodes_bare"],
                      f"{r['max_drive_in_speed']:.3f}", f"{r['max_drive_in_speed_bare']:.3f}",
                      r["contact_episodes"], r["contact_episodes_bare"], f"{r['success']:.2f}",
                      f"{r['success_bare']:.2f}", f"{r['success_clear']:.2f}", f"{r['success_clear_bare']:.2f}",
                      *(_tick(r[k]) for k in ("min_gap_mm", "min_gap_mm_bare",
                                                                          "median_min_gap_mm",
                                                                          "median_min_gap_mm_bare"))]
                     for name, by in doc["intruders"].items() for tag, r in by.items()])
        print()
    if "clutter" in doc:
        print_table(*clutter_table(doc["clutter"]))
        print()
    if "latency_ms" in doc:
        modules = [("in memory", doc["latency_ms"]), ("TorchScript module", doc["latency_ms_torchscript_module"])]
        print_table(["policy", "robots", "tick p50 [ms]", "p99", "observe p50", "policy p50", "p99", "safety p50",
                     "p99", "mec p50", "geometry"],
                    [[label, n, *(f"{r[k]:.3f}" for k in ("p50", "p99", "observe_p50", "policy_p50", "policy_p99",
                                                           "safety_p50", "safety_p99", "mec_p50")), r["geometry"]]
                     for label, rows in modules for n, r in rows.items()])
        print()
        print_table(["file format", "robots", "tick p50 [ms]", "p99", "policy stage p50", "p99",
                     "tick vs in memory"],
                    [[fmt, n, *(f"{r[k]:.3f}" for k in ("p50", "p99", "policy_stage_p50", "policy_stage_p99")),
                      f"{r['p50'] / doc['latency_ms'][n]['p50']:.2f}x" if n in doc["latency_ms"] else "-"]
                     for fmt, rows in doc["latency_ms_by_format"].items() for n, r in rows.items()])


if __name__ == "__main__":
    sys.exit(main())
