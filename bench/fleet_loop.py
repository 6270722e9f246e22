"""State -> command round trip over Zenoh between two processes, at 50 Hz, for N robots.

Robot process (a child of this script): N :class:`deploy.robot_link.RobotLink` sharing one
session. Every 20 ms it publishes the N states and waits until each robot holds the command
answering its state (``state_seq``); the round trip of a tick is the time from the first
publish to the last answer, on the robot process's clock. A tick whose round trip exceeds the
20 ms period is a deadline miss; ``unanswered`` counts the misses that got no full answer
within 100 ms (a lost message or a stalled process; recorded as 100 ms).

Controller process (this script): :class:`deploy.bridge.Bridge` with a trivial controller
(``a = -0.5 v``; the transport and the bridge are measured, not a policy).

Peer in the same run (``peer_raw_zenoh``): the same N messages of 64 bytes per tick echoed by
a bare Zenoh subscriber/publisher pair, without the wire format, validation or the bridge (the
same sessions and publisher settings: :func:`deploy.network.declare_data_publisher`).

Through a router with mutual TLS (``tls_router``, ``--tls``): the same bridge and robots as
clients of a ``formation router`` (:mod:`deploy.router`: TLS with the certificates of a fresh
fleet CA, the fleet's access control on), the router in this script's process; every message
crosses two TLS links and the router. Compare its p50 with the plain peer-to-peer row. The
router does not count refusals here (``RouterConfig.count`` off, the library default); counting,
on in ``formation router``, cost about 8 % at p50 with 50 robots (10.3-10.7 against 9.5 ms,
2026-12-02).

    python bench/fleet_loop.py                       # N = 5, 20, 50; 1000 ticks each
    python bench/fleet_loop.py --robots 5 --ticks 200 --json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._common import (  # noqa: E402
    positive_int,
    positive_int_list,
    print_json,
    print_table,
    progress,
)
from deploy.bridge import Bridge, BridgeConfig  # noqa: E402
from deploy.certs import CONTROLLER, FLEET_SIM, ROUTER, NodeFiles, make_certs  # noqa: E402
from deploy.network import TransportConfig, declare_data_publisher, free_tcp_port  # noqa: E402
from deploy.robot_link import RobotLink  # noqa: E402
from deploy.router import Router, RouterConfig  # noqa: E402
from deploy.wire import RobotRegistry  # noqa: E402

PERIOD_S = 0.02
ANSWER_TIMEOUT_S = 0.1
FLEET = "bench"
RAW_PAYLOAD_BYTES = 64


def ping_payload(tick: int) -> bytes:
    """The raw peer's ping of ``tick``: 64 bytes, the tick number in the first 8 (the echo
    returns the payload unchanged, so the pong names the tick it answers)."""
    return tick.to_bytes(8, "little").ljust(RAW_PAYLOAD_BYTES, b"\0")


def payload_tick(payload: bytes) -> int:
    """The tick number a ping or pong carries (:func:`ping_payload`)."""
    return int.from_bytes(payload[:8], "little")


class PongCounter:
    """Which robots answered the raw peer's current tick. A pong counts only when it carries
    the current tick's number: the late pong of a tick that timed out answers no later tick."""

    def __init__(self, robots: int) -> None:
        self.robots = robots
        self.tick = 0
        self._answered: set[int] = set()

    def start(self) -> int:
        """Begin the next tick; its number, for :func:`ping_payload`."""
        self.tick += 1
        self._answered = set()
        return self.tick

    def record(self, robot: int, tick: int) -> None:
        """A pong of ``robot`` carrying ``tick``."""
        if tick == self.tick:
            self._answered.add(robot)

    def complete(self) -> bool:
        """Every robot answered the current tick."""
        return len(self._answered) == self.robots


def names(n: int) -> tuple[str, ...]:
    return tuple(f"b{i}" for i in range(n))


def stats(rtts_ms: list[float], missed: int, unanswered: int) -> dict:
    a = np.asarray(rtts_ms) if rtts_ms else np.asarray([float("nan")])
    return {"ticks": len(rtts_ms), "p50_ms": round(float(np.percentile(a, 50)), 4),
            "p99_ms": round(float(np.percentile(a, 99)), 4),
            "max_ms": round(float(a.max()), 4), "missed": int(missed),
            "unanswered": int(unanswered)}


def paced(ticks: int, one_tick) -> dict:
    """Run ``one_tick() -> round trip [s] | None`` every PERIOD_S; collect round trips."""
    rtts, missed, unanswered = [], 0, 0
    next_time = time.monotonic()
    for _ in range(ticks):
        rtt = one_tick()
        if rtt is None:
            missed += 1
            unanswered += 1
            rtts.append(ANSWER_TIMEOUT_S * 1e3)
        else:
            rtts.append(rtt * 1e3)
            missed += rtt > PERIOD_S
        next_time += PERIOD_S
        time.sleep(max(0.0, next_time - time.monotonic()))
    return stats(rtts, missed, unanswered)


# ---------------------------------------------------------------------- robot process
def robot_process(n: int, port: int, ticks: int, certs: str | None = None) -> int:
    if certs is None:
        config = TransportConfig(connect=(f"tcp/127.0.0.1:{port}",))
    else:          # one session holds every robot: the fleet-sim identity
        config = TransportConfig(connect=(f"tls/127.0.0.1:{port}",), mode="client",
                                 tls=NodeFiles.in_dir(certs, FLEET_SIM))
    registry = RobotRegistry(names(n))
    with config.open() as session:
        links = [RobotLink(FLEET, r, registry, session) for r in registry.names]
        if not all(link.wait_for(lambda lk=link: lk.controller_alive, 30.0) for link in links):
            print(json.dumps({"error": "controller not seen"}), flush=True)
            return 1
        time.sleep(0.5)  # let the controller see every robot's liveliness token

        def ours() -> float | None:
            t0 = time.perf_counter()
            sent = [link.publish_state((0.5, 0.5), (0.1, 0.0)) for link in links]
            deadline = t0 + ANSWER_TIMEOUT_S
            for link, msg in zip(links, sent, strict=True):
                ok = link.wait_for(lambda lk=link, s=msg.seq: lk.latest_command is not None
                                   and lk.latest_command.msg.state_seq >= s,
                                   max(0.0, deadline - time.perf_counter()))
                if not ok:
                    return None
            return time.perf_counter() - t0

        for _ in range(20):
            ours()
        result = {"ours": paced(ticks, ours)}
        for link in links:
            link.close()
        if certs is not None:             # the router's access control knows no raw keys
            print(json.dumps(result), flush=True)
            return 0

        pongs = threading.Condition()
        counter = PongCounter(n)
        subscriber = session.declare_subscriber("fleetloop/raw/*/pong",
                                                zenoh.handlers.FifoChannel(4 * n + 16))

        def drain() -> None:
            while True:
                try:
                    sample = subscriber.handler.recv()
                except zenoh.ZError:
                    return
                i = int(str(sample.key_expr).split("/")[2])
                with pongs:
                    counter.record(i, payload_tick(sample.payload.to_bytes()))
                    pongs.notify_all()

        drainer = threading.Thread(target=drain, daemon=True)
        drainer.start()
        pubs = [declare_data_publisher(session, f"fleetloop/raw/{i}/ping", zenoh.CongestionControl.DROP)
                for i in range(n)]
        time.sleep(0.3)

        def raw() -> float | None:
            with pongs:
                payload = ping_payload(counter.start())
            t0 = time.perf_counter()
            for pub in pubs:
                pub.put(payload)
            with pongs:
                ok = pongs.wait_for(counter.complete, ANSWER_TIMEOUT_S)
            return time.perf_counter() - t0 if ok else None

        for _ in range(20):
            raw()
        result["raw"] = paced(ticks, raw)
        for pub in pubs:
            pub.undeclare()
        subscriber.undeclare()
        # A thread still on its way out of Zenoh's recv when the interpreter finalises is
        # ended inside a Rust frame, and glibc aborts the process ("FATAL: exception not
        # rethrown") after the result is printed: wait for it.
        drainer.join(timeout=5.0)
    print(json.dumps(result), flush=True)
    return 0


# ---------------------------------------------------------------------- controller side
def measure_tls(n: int, ticks: int) -> dict:
    """The bridge and the robots through a router with mutual TLS (module docstring)."""
    registry = RobotRegistry(names(n))
    port = free_tcp_port()
    with tempfile.TemporaryDirectory() as certs:
        make_certs(certs, [ROUTER, CONTROLLER, FLEET_SIM])
        config = RouterConfig(FLEET, registry.names, NodeFiles.in_dir(certs, ROUTER),
                              (f"tls/127.0.0.1:{port}",))
        with Router(config):
            transport = TransportConfig(connect=(f"tls/127.0.0.1:{port}",), mode="client",
                                        tls=NodeFiles.in_dir(certs, CONTROLLER))
            zeros = {r: np.zeros(2) for r in registry.names}
            bridge = Bridge(FLEET, registry, transport, lambda s: -0.5 * s.velocities, targets=zeros,
                            object_pose=np.zeros(3), config=BridgeConfig(ttl_ms=100))
            loop = threading.Thread(target=bridge.run, daemon=True)
            loop.start()
            child = subprocess.run([sys.executable, __file__, "--robot-process", str(n), "--port",
                                    str(port), "--ticks", str(ticks), "--certs", certs],
                                   capture_output=True, text=True, timeout=60 + 3 * ticks * PERIOD_S)
            bridge.stop()
            loop.join(timeout=2)
            bridge.close()
    if child.returncode != 0:
        raise RuntimeError(f"robot process failed: {child.stdout} {child.stderr[-2000:]}")
    return json.loads(child.stdout.strip().splitlines()[-1])["ours"]


def measure(n: int, ticks: int) -> dict:
    port = free_tcp_port()
    transport = TransportConfig(listen=(f"tcp/127.0.0.1:{port}",))
    registry = RobotRegistry(names(n))
    zeros = {r: np.zeros(2) for r in registry.names}
    bridge = Bridge(FLEET, registry, transport, lambda s: -0.5 * s.velocities, targets=zeros,
                    object_pose=np.zeros(3), config=BridgeConfig(ttl_ms=100))
    session = bridge.link.session
    echo_sub = session.declare_subscriber("fleetloop/raw/*/ping", zenoh.handlers.FifoChannel(4096))
    echo_pubs: dict[str, zenoh.Publisher] = {}

    def echo() -> None:
        while True:
            try:
                sample = echo_sub.handler.recv()
            except zenoh.ZError:
                return
            key = str(sample.key_expr).replace("/ping", "/pong")
            if key not in echo_pubs:
                echo_pubs[key] = declare_data_publisher(session, key, zenoh.CongestionControl.DROP)
            echo_pubs[key].put(sample.payload)

    echoer = threading.Thread(target=echo, daemon=True)
    echoer.start()
    loop = threading.Thread(target=bridge.run, daemon=True)
    loop.start()
    child = subprocess.run([sys.executable, __file__, "--robot-process", str(n), "--port",
                            str(port), "--ticks", str(ticks)], capture_output=True, text=True,
                           timeout=60 + 3 * ticks * PERIOD_S)
    bridge.stop()
    loop.join(timeout=2)
    echo_sub.undeclare()
    echoer.join(timeout=5.0)
    for pub in echo_pubs.values():
        pub.undeclare()
    bridge.close()
    if child.returncode != 0:
        raise RuntimeError(f"robot process failed: {child.stdout} {child.stderr[-2000:]}")
    return json.loads(child.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robots", type=positive_int_list, default=[5, 20, 50],
                        help="robot counts, comma-separated (default 5,20,50)")
    parser.add_argument("--ticks", type=positive_int, default=1000, help="ticks per count (default 1000)")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    parser.add_argument("--tls", action=argparse.BooleanOptionalAction, default=True,
                        help="also the bridge and robots through a router with mutual TLS (default on)")
    parser.add_argument("--robot-process", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--certs", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.robot_process is not None:
        return robot_process(args.robot_process, args.port, args.ticks, args.certs)
    document: dict = {}
    peer: dict = {}
    tls: dict = {}
    for n in args.robots:
        progress(f"fleet_loop: {n} robots, {args.ticks} ticks at {1 / PERIOD_S:.0f} Hz")
        result = measure(n, args.ticks)
        document[str(n)] = result["ours"]
        peer[str(n)] = result["raw"]
        if args.tls:
            progress(f"fleet_loop: {n} robots through a router, mutual TLS")
            tls[str(n)] = measure_tls(n, args.ticks)
    document["peer_raw_zenoh"] = peer
    if args.tls:
        document["tls_router"] = tls
        for n in args.robots:      # the cost of TLS and the router, as the p50 ratio to plain
            tls[str(n)]["p50_vs_plain"] = round(tls[str(n)]["p50_ms"] / document[str(n)]["p50_ms"], 3)
    if args.json:    # keyed by robot count (#17's shape, read by other tools): no extra key
        print_json(document, provenance=False)
        return 0
    headers = ["robots", "path", "ticks", "p50 ms", "p99 ms", "max ms", "missed", "of them unanswered"]
    rows = []
    for n in args.robots:
        paths = [("bridge+wire", document[str(n)]), ("raw zenoh", peer[str(n)])]
        if args.tls:
            paths.append(("bridge+wire, TLS via router", tls[str(n)]))
        for path, r in paths:
            rows.append([n, path, r["ticks"], r["p50_ms"], r["p99_ms"], r["max_ms"], r["missed"],
                         r["unanswered"]])
    print_table(headers, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
