"""Intruders against a fleet behind `formation router`, for tests/deploy/test_fleet_over_tls.py
(run as a script, or :func:`intrude` in process).

1. With a valid robot certificate (``--as r1``): publish well-formed, fresh commands for every
   robot, an e-stop, and a forged state of r0, 20 rounds, 10 ms apart.
2. With a self-signed "controller" certificate (a CA of its own, ``--rogue``): try to link.
3. With no certificate, over plain tcp to the router's port: try to link.

Prints (script) or returns one JSON document: ``{"messages": sent, "links_refused": refused}``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import zenoh

from deploy.certs import CONTROLLER, NodeFiles
from deploy.network import TransportConfig
from deploy.wire import CmdMsg, EstopMsg, StateMsg, encode


def intrude(fleet: str, robots: int, endpoint: str, certs: str, rogue: str, holder: str = "r1") -> dict:
    attempts = {"messages": 0, "links_refused": 0}
    with TransportConfig(connect=(endpoint,), mode="client", tls=NodeFiles.in_dir(certs, holder)).open() as s:
        now = time.monotonic_ns()
        for k in range(1, 21):
            for rid in range(robots):
                s.put(f"formation/{fleet}/robot/r{rid}/cmd", encode(CmdMsg(rid, 31337, k, now, (1.0, 0.0), 500)))
            s.put(f"formation/{fleet}/estop", encode(EstopMsg(31337, k, now, True)))
            s.put(f"formation/{fleet}/robot/r0/state", encode(StateMsg(0, 31337, k, now, (0.9, 0.9), (0.0, 0.0))))
            attempts["messages"] += robots + 2
            time.sleep(0.01)
    plain = zenoh.Config()
    plain.insert_json5("mode", '"client"')
    plain.insert_json5("connect/endpoints", json.dumps([endpoint.replace("tls/", "tcp/", 1)]))
    for open_session in (lambda: TransportConfig(connect=(endpoint,), mode="client",
                                                 tls=NodeFiles.in_dir(rogue, CONTROLLER)).open(),
                         lambda: zenoh.open(plain)):
        try:
            open_session().close()
        except zenoh.ZError:
            attempts["links_refused"] += 1
    return attempts


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--fleet", required=True)
    p.add_argument("--robots", type=int, required=True)
    p.add_argument("--endpoint", required=True)
    p.add_argument("--certs", required=True)
    p.add_argument("--rogue", required=True)
    p.add_argument("--as", dest="holder", default="r1")
    args = p.parse_args()
    print(json.dumps(intrude(args.fleet, args.robots, args.endpoint, args.certs, args.rogue, args.holder)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
