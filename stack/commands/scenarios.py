"""`formation scenarios`: list the task presets, or show one in full."""

from __future__ import annotations

import json
import sys

from sim.scenario import PRESETS, ScenarioError, make_scenario


def register(sub) -> None:
    p = sub.add_parser("scenarios", help="list the scenario presets (or show one with --show NAME)",
                       description="List the formation-change presets. transport-N gives the default "
                                   "layout for any N in 1..21.")
    p.add_argument("--show", metavar="NAME", help="print one preset (or transport-N) as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    if args.show:
        try:
            print(json.dumps(make_scenario(args.show).to_dict(), indent=2))
        except ScenarioError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        return 0
    width = max(map(len, PRESETS))
    for name, text in PRESETS.items():
        sc = make_scenario(name)
        print(f"{name:<{width}}  N={sc.num_robots:<2d}  {text}")
    print(f"{'transport-N':<{width}}  N=1..21 the default layout for any N")
    return 0
