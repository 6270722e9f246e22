"""`formation router`: the fleet's Zenoh router, mutual TLS and access control (deploy/router.py).

Only the controller's certificate may command robots or touch the e-stop; robot `rid` may
publish only its own state and token (deploy/security.py). Runs until Ctrl-C / SIGTERM.

    formation router --fleet f1 --scenario paper-5 --certs certs --listen tls/0.0.0.0:7447

What it refuses is counted from Zenoh's own log (deploy/access_log.py): messages its access
control denied, by sender, kind and key, and TLS links it refused, by reason; new ones are logged
at most once a second on stderr, and the totals printed as JSON on exit (and written to --report):
"denied" and "withheld" {identity: {"<kind> <key>": n}}, "refused_links" {reason: n}, "counting".
--no-count turns the counting off (it routes this process's stdout through a pipe and costs a
log line per routed message; README, fleet security).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys

import zenoh

from deploy.fleet_sim import robot_names, write_json
from deploy.router import Router, router_config
from sim.scenario import make_scenario
from stack.commands.argtypes import add_deprecated_alias, lease_ms, out_file


def register(sub) -> None:
    p = sub.add_parser("router", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fleet", required=True, help="fleet name (Zenoh key chunk)")
    p.add_argument("--scenario", default="paper-5", help="its robots r0..r{N-1} (default paper-5)")
    p.add_argument("--robot-ids", default=None, metavar="A,B,...",
                   help="robot ids instead of the scenario's (comma-separated)")
    add_deprecated_alias(p, "--robots", "--robot-ids")
    p.add_argument("--certs", required=True, metavar="DIR", help="folder made by `formation certs`")
    p.add_argument("--listen", action="append", default=[], metavar="tls/HOST:PORT",
                   help="endpoint to listen on (default tls/127.0.0.1:7447); repeat for several")
    p.add_argument("--lease-ms", type=lease_ms, default=None, metavar="MS",
                   help="link lease [ms], >= 100 (Zenoh default 10000)")
    p.add_argument("--report", type=out_file, default=None, metavar="FILE",
                   help="write the JSON exit report to FILE too")
    p.add_argument("--count", action=argparse.BooleanOptionalAction, default=True,
                   help="count denied messages and refused links from Zenoh's log (default on; "
                        "--no-count: no stdout pipe, no log line per routed message)")
    p.set_defaults(func=run)


def run(args) -> int:
    try:
        robots = (args.robot_ids.split(",") if args.robot_ids
                  else robot_names(make_scenario(args.scenario).num_robots))
        config = router_config(args.fleet, robots, args.certs, args.listen or ["tls/127.0.0.1:7447"],
                               args.lease_ms, args.count)
        router = Router(config)
    except (ValueError, OSError, zenoh.ZError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: router.stop())
    print(f"router {args.fleet}: listening on {', '.join(config.listen)}, robots {', '.join(config.robots)}",
          file=sys.stderr, flush=True)
    with router:
        router.serve()
    summary = router.summary()      # after close: the tap has given stdout back
    if args.report:
        write_json(args.report, summary)
    print(json.dumps(summary), flush=True)
    return 0
