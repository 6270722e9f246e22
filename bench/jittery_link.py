"""A fleet over a slow link whose delay jitters: how long the stack takes to bring it home, and
whether anything touches, against the same fleet driven bare.

``formation fleet-sim`` (paper-5, real time at 20 Hz, the scripted controller's fleet) listens
on 127.0.0.1; ``formation bridge`` connects to it through :class:`deploy.delay_relay.DelayRelay`,
which holds every byte ``--delay-ms`` +- ``--jitter-ms`` each way. Each configuration (the
bridge's flags) runs ``--seeds`` episodes (fleet-sim ``--seed k``) of ``--episode-ticks`` ticks:

* ``stack``: filter, MEC, docking (the defaults);
* ``bare``: ``--no-safety --no-mec`` (the peer: the same controller with nothing in between);
* ``filter``: ``--no-mec``; ``mec``: ``--no-safety``.

Per run: ``home_tick`` (the first tick at which every robot is within the scenario's tolerance
of a distinct target, None if never), contacts (robot, object, wall onsets), the bridge's
command round trips [ms] and the share of robot ticks braked by the robots' own watchdog.

    python bench/jittery_link.py                               # 20 +- 10 ms, 3 seeds, stack and bare
    python bench/jittery_link.py --configs stack,bare,filter,mec --json
    python bench/jittery_link.py --playout-ticks 2               # robots with a playout buffer

JSON (``ticks``: ``--episode-ticks``): ``{"delay_ms", "jitter_ms", "ticks", "brake_after_ticks",
"playout_ticks", "gather_s", "rows":
[{"config", "seed", "home_tick", "collisions", "round_trip_ms": {"p50", "p99"},
"watchdog_share"}, ...]}``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench._common import positive_int, print_json, print_table, progress  # noqa: E402
from deploy.bridge import BridgeConfig  # noqa: E402
from deploy.delay_relay import DelayRelay  # noqa: E402
from deploy.network import free_tcp_port  # noqa: E402
from sim.scenario import make_scenario  # noqa: E402
from stack.commands import argtypes  # noqa: E402

CONFIGS = {"stack": [], "bare": ["--no-safety", "--no-mec"], "filter": ["--no-mec"], "mec": ["--no-safety"]}


def config_list(text: str) -> list[str]:
    names = [x for x in text.split(",") if x]
    unknown = [x for x in names if x not in CONFIGS]
    if not names or unknown:
        raise argparse.ArgumentTypeError(f"--configs takes a comma-separated list of {sorted(CONFIGS)}, "
                                         f"got {text!r}")
    return names


def home_tick(trace: list[dict], targets: np.ndarray, tolerance: float) -> int | None:
    """The first tick whose positions lie within ``tolerance`` of distinct targets."""
    for entry in trace:
        gaps = np.linalg.norm(np.array(entry["positions"])[:, None] - targets[None], axis=2)
        rows, cols = linear_sum_assignment(gaps)
        if (gaps[rows, cols] <= tolerance).all():
            return int(entry["tick"])
    return None


def run(config: str, seed: int, args: argparse.Namespace) -> dict:
    """One episode of fleet-sim and the bridge over the relay; the row of the module docstring."""
    cli = [sys.executable, "-m", "stack.cli"]
    with tempfile.TemporaryDirectory() as tmp:
        port = free_tcp_port()
        sim = subprocess.Popen([*cli, "fleet-sim", "--fleet", "jl", "--scenario", "paper-5", "--rate-hz", "20",
                                "--listen", f"tcp/127.0.0.1:{port}", "--report", f"{tmp}/sim.json",
                                "--ticks", str(args.episode_ticks), "--seed", str(seed),
                                "--brake-after-ticks", str(args.brake_after_ticks),
                                "--playout-ticks", str(args.playout_ticks)],
                               cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            with DelayRelay(port, args.delay_ms / 1e3, args.jitter_ms / 1e3, seed=seed) as relay:
                bridge = subprocess.Popen([*cli, "bridge", "--fleet", "jl", "--scenario", "paper-5",
                                           "--connect", f"tcp/127.0.0.1:{relay.port}", "--policy", "scripted",
                                           "--report", f"{tmp}/bridge.json", "--gather", str(args.gather),
                                           *CONFIGS[config]],
                                          cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                try:
                    if sim.wait(timeout=args.episode_ticks * 0.05 + 120) != 0:
                        raise RuntimeError(f"fleet-sim failed: {sim.stderr.read()[-2000:]}")
                finally:
                    bridge.terminate()
                    bridge.wait(timeout=60)
        finally:
            if sim.poll() is None:
                sim.kill()
        report = json.loads(Path(f"{tmp}/sim.json").read_text())
        trips = json.loads(Path(f"{tmp}/bridge.json").read_text())["round_trip_ms"]
    scenario = make_scenario("paper-5")
    applied = [mode for entry in report["trace"] for mode in entry["applied"]]
    return {"config": config, "seed": seed,
            "home_tick": home_tick(report["trace"], scenario.targets, scenario.target_tolerance),
            "collisions": report["collisions"], "round_trip_ms": {"p50": trips["p50"], "p99": trips["p99"]},
            "watchdog_share": applied.count("watchdog") / max(len(applied), 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--delay-ms", type=float, default=20.0, metavar="MS",
                        help="mean hold of the relay, each way [ms] (default 20)")
    parser.add_argument("--jitter-ms", type=float, default=10.0, metavar="MS",
                        help="the hold is uniform in delay +- this, at most the delay [ms] (default 10)")
    parser.add_argument("--seeds", type=positive_int, default=3,
                        help="episodes per configuration, fleet-sim seeds 0..K-1 (default 3)")
    parser.add_argument("--episode-ticks", type=positive_int, default=400, metavar="T",
                        help="fleet ticks per episode, at 20 Hz (default 400)")
    argtypes.add_deprecated_alias(parser, "--ticks", "--episode-ticks")
    parser.add_argument("--brake-after-ticks", type=positive_int, default=2, metavar="K",
                        help="fleet-sim's watchdog: brake after this many ticks without a fresh command "
                             "(default 2)")
    parser.add_argument("--playout-ticks", type=int, default=0, metavar="D",
                        help="fleet-sim's playout buffer: robots act on each command D ticks after the "
                             "state it answers (default 0: on arrival)")
    parser.add_argument("--gather", type=float, default=BridgeConfig.gather_s, metavar="S",
                        help="the bridge's --gather: how long a tick waits for the rest of a burst of "
                             f"states [s] (default {BridgeConfig.gather_s}, the bridge's)")
    parser.add_argument("--configs", type=config_list, default=["stack", "bare"],
                        help=f"comma-separated, of {', '.join(CONFIGS)} (default stack,bare)")
    parser.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    args = parser.parse_args(argv)
    if not 0 <= args.jitter_ms <= args.delay_ms:
        parser.error(f"--jitter-ms must lie in [0, --delay-ms], got {args.jitter_ms} for {args.delay_ms}")
    if not args.gather >= 0:
        parser.error(f"--gather must be >= 0 seconds, got {args.gather}")
    if args.playout_ticks < 0:
        parser.error(f"--playout-ticks must be >= 0, got {args.playout_ticks}")
    rows = []
    start = time.monotonic()
    for config in args.configs:
        for seed in range(args.seeds):
            progress(f"jittery link: {config} seed {seed} ({time.monotonic() - start:.0f} s)")
            rows.append(run(config, seed, args))
    if args.json:
        print_json({"delay_ms": args.delay_ms, "jitter_ms": args.jitter_ms, "ticks": args.episode_ticks,
                    "brake_after_ticks": args.brake_after_ticks, "playout_ticks": args.playout_ticks,
                    "gather_s": args.gather, "rows": rows})
        return 0
    print_table(["config", "seed", "home tick", "contacts (robot/object/wall)", "round trip p50 [ms]", "p99",
                 "watchdog-braked ticks"],
                [(r["config"], r["seed"], r["home_tick"] if r["home_tick"] is not None else f"> {args.episode_ticks}",
                  "/".join(str(r["collisions"][k]) for k in ("robot", "object", "wall")),
                  f"{r['round_trip_ms']['p50']:.1f}", f"{r['round_trip_ms']['p99']:.1f}",
                  f"{100 * r['watchdog_share']:.1f} %") for r in rows])
    return 0


if __name__ == "__main__":
    sys.exit(main())
