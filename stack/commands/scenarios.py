"""`formation scenarios`: list the task presets and scenario distributions, or show one in full.

``--show NAME`` prints a scenario, ``--show-distribution NAME`` a training distribution
(:mod:`sim.distribution`), each as JSON that is a valid file for ``--scenario`` /
``formation train --distribution``.
"""

from __future__ import annotations

import json
import sys

from sim.distribution import DISTRIBUTIONS, DistributionError, load_distribution
from sim.scenario import PRESETS, ScenarioError, make_scenario


def register(sub) -> None:
    p = sub.add_parser("scenarios", description="List the formation-change presets. transport-N gives the default "
                                   "layout for any N in 1..21.")
    p.add_argument("--show", metavar="NAME", help="print one preset (or transport-N) as JSON")
    p.add_argument("--show-distribution", metavar="NAME",
                   help=f"print a training distribution ({', '.join(DISTRIBUTIONS)}, or a file) as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    if args.show or args.show_distribution:
        try:
            data = (make_scenario(args.show).to_dict() if args.show
                    else load_distribution(args.show_distribution).to_dict())
        except (ScenarioError, DistributionError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(json.dumps(data, indent=2))
        return 0
    width = max(map(len, PRESETS))
    for name, text in PRESETS.items():
        sc = make_scenario(name)
        print(f"{name:<{width}}  N={sc.num_robots:<2d}  {text}")
    print(f"{'transport-N':<{width}}  N=1..21 the default layout for any N")
    print("\ntraining distributions (formation train --distribution NAME):")
    for name in DISTRIBUTIONS:
        print(f"  {name}")
    return 0
