"""`formation estop`: an operator engages, releases or queries the fleet e-stop of a running
`formation bridge` (deploy/operator_channel.py ``operator_answer``).

    formation estop --fleet lab --engage  --connect tcp/127.0.0.1:7447
    formation estop --fleet lab --release --connect tcp/127.0.0.1:7447
    formation estop --fleet lab --status  --certs certs --identity operator --connect tls/10.0.0.1:7447

``--release`` is refused while a live robot is silent past the bridge's ``--estop-after``: the
rule that raised the e-stop would raise it again. Prints the bridge's answer as JSON; exit 0 when
the request was carried out, 1 when the bridge refused it, 2 when no bridge answered.
"""

from __future__ import annotations

import argparse
import json
import sys

import zenoh

from deploy.network import FleetKeys
from stack.commands import argtypes


def register(sub) -> None:
    p = sub.add_parser("estop", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fleet", required=True, help="fleet name (Zenoh key chunk)")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--engage", action="store_const", const="engage", dest="request",
                      help="latch the fleet e-stop now")
    what.add_argument("--release", action="store_const", const="release", dest="request",
                      help="release it (refused while a robot is silent)")
    what.add_argument("--status", action="store_const", const="status", dest="request",
                      help="report the e-stop and the longest-silent robot")
    p.add_argument("--timeout", type=argtypes.seconds, default=5.0, metavar="S",
                   help="seconds to wait for the bridge's answer (default 5)")
    argtypes.add_transport_flags(p, "operator")
    p.set_defaults(func=run)


def run(args) -> int:
    try:
        keys = FleetKeys(args.fleet)
        transport = argtypes.transport_config(args)
        session = transport.open()
    except (ValueError, OSError, zenoh.ZError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    answer = None
    with session:
        for reply in session.get(keys.operator, payload=args.request.encode(), timeout=args.timeout):
            if reply.ok is not None:
                try:
                    answer = json.loads(reply.ok.payload.to_bytes())
                except ValueError:
                    answer = None
                if not isinstance(answer, dict):
                    print(f"error: the answer on {keys.operator} is not a JSON object: is a bridge of "
                          f"fleet {args.fleet!r} answering there?", file=sys.stderr)
                    return 2
                break
    if answer is None:
        print(f"error: no bridge of fleet {args.fleet!r} answered within {args.timeout} s "
              "(is it running, on these endpoints?)", file=sys.stderr)
        return 2
    print(json.dumps(answer))
    return 0 if answer.get("ok") else 1
