"""`formation certs`: a fleet CA and one certificate per node (controller, fleet-sim, router,
operator, tracker, each robot), for mutual TLS through `formation router`. See deploy/certs.py and
deploy/security.py.

    formation certs --out certs --scenario paper-5 --host 10.0.0.1
    formation router --fleet f1 --scenario paper-5 --certs certs --listen tls/0.0.0.0:7447
    formation fleet-sim --fleet f1 --scenario paper-5 --certs certs --connect tls/10.0.0.1:7447
    formation bridge --fleet f1 --scenario paper-5 --certs certs --connect tls/10.0.0.1:7447
"""

from __future__ import annotations

import argparse
import sys

from deploy.certs import (
    CONTROLLER,
    FLEET_SIM,
    OPERATOR,
    ROUTER,
    TRACKER,
    check_robot_ids,
    make_certs,
)
from deploy.fleet_sim import robot_names
from sim.scenario import make_scenario
from stack.commands import argtypes


def register(sub) -> None:
    p = sub.add_parser("certs", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=argtypes.out_folder, required=True, metavar="DIR",
                   help="folder for ca.pem/.key and <node>.pem/.key (made if missing)")
    p.add_argument("--scenario", default="paper-5",
                   help="robots r0..r{N-1} of this preset or scenario file (default paper-5)")
    p.add_argument("--robot-ids", default=None, metavar="A,B,...",
                   help="robot ids instead of the scenario's (comma-separated)")
    argtypes.add_deprecated_alias(p, "--robots", "--robot-ids")
    p.add_argument("--host", action="append", default=[], metavar="NAME_OR_IP",
                   help="a name or address the router is reached at (besides localhost, "
                        "127.0.0.1); repeat for several")
    p.add_argument("--days", type=argtypes.positive, default=365, metavar="DAYS",
                   help="validity in days (default 365)")
    p.set_defaults(func=run)


def run(args) -> int:
    try:
        robots = check_robot_ids(args.robot_ids.split(",") if args.robot_ids
                                 else robot_names(make_scenario(args.scenario).num_robots))
        files = make_certs(args.out, [ROUTER, CONTROLLER, FLEET_SIM, OPERATOR, TRACKER, *robots], args.host, args.days)
    except (ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}/ca.pem and certificates for {', '.join(files)} "
          "(keep ca.key off the robots)", file=sys.stderr)
    return 0
