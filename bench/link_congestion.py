"""Robot messages over a link too slow for them: how late they arrive, and how many at all.

Two network namespaces joined by a veth pair (addresses 10.78.0.1 and .2, made here and removed
after), the sender's side shaped by a token bucket (``tc qdisc ... tbf``, ``--rate-kbit``). The
sender publishes a burst of ``--burst`` 52-byte messages, one per robot, every ``--period-ms``
(a controller's commands, stamped with the sender's monotonic clock, which both namespaces
share); the receiver records each message's age on arrival. Two sets of publishers take turns, ``--repeats`` times:

* ``fleet``: the fleet's state and command publishers (:func:`deploy.network.declare_data_publisher`:
  DROP, not express: one tick's burst shares a batch);
* ``express``: the same with Zenoh's express flag, as the links had before 2026-12-03 (the peer).

On a link too slow for the traffic, neither keeps messages fresh: TCP and the token bucket
queue them before Zenoh can drop any. What a controller can do is measure the delay and plan
over it: the bridge's round trips (``command_delay_s``) feed the safety filter's latency bound.
Needs root (``ip netns``, ``tc``).

    sudo python bench/link_congestion.py                  # 1000 kbit/s, 50 robots, 20 ms, 4 s
    sudo python bench/link_congestion.py --rate-kbit 500 --repeats 1 --json

JSON (``robots``: ``--burst``): ``{"rate_kbit", "robots", "period_ms", "ticks", "rows":
[{"publishers", "sent", "received", "age_ms": {"p50", "p99", "max"}}, ...]}``, one row per run.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench._common import positive_int, print_json, print_table, progress  # noqa: E402
from stack.commands import argtypes  # noqa: E402

SENDER, RECEIVER = "10.78.0.1", "10.78.0.2"
PORT = 7447
STAMP = struct.Struct("<qi")  # send time [ns, monotonic], tick
PAD = bytes(40)
DRAIN_S = 3.0  # [s] the receiver keeps listening after the sender has closed


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=10)


class ShapedLink:
    """Two namespaces and a veth pair, the sender's end limited to ``rate_kbit`` (context manager)."""

    def __init__(self, rate_kbit: int):
        tag = f"lc{os.getpid() % 100000}"
        self.sender, self.receiver = f"{tag}s", f"{tag}r"
        self.rate_kbit = rate_kbit

    def __enter__(self) -> ShapedLink:
        try:
            for ns in (self.sender, self.receiver):
                _ip("netns", "add", ns)
                _ip("-n", ns, "link", "set", "lo", "up")
            a, b = f"{self.sender}v", f"{self.receiver}v"
            _ip("link", "add", a, "netns", self.sender, "type", "veth", "peer", "name", b,
                "netns", self.receiver)
            _ip("-n", self.sender, "addr", "add", f"{SENDER}/30", "dev", a)
            _ip("-n", self.receiver, "addr", "add", f"{RECEIVER}/30", "dev", b)
            _ip("-n", self.sender, "link", "set", a, "up")
            _ip("-n", self.receiver, "link", "set", b, "up")
            subprocess.run(["ip", "netns", "exec", self.sender, "tc", "qdisc", "add", "dev", a, "root",
                            "tbf", "rate", f"{self.rate_kbit}kbit", "burst", "8kb", "latency", "100ms"],
                           check=True, capture_output=True, timeout=10)
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc) -> None:
        for ns in (self.sender, self.receiver):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)


# ---------------------------------------------------------------------- the two processes
def receive() -> int:
    """Receiver role: listen, print ``ready``, record ages until a line on stdin, print them as JSON."""
    from deploy.network import TransportConfig

    ages: list[float] = []
    lock = threading.Lock()

    def on_sample(sample) -> None:
        sent_ns, _ = STAMP.unpack_from(sample.payload.to_bytes())
        with lock:
            ages.append((time.monotonic_ns() - sent_ns) / 1e6)

    with TransportConfig(listen=(f"tcp/{RECEIVER}:{PORT}",), insecure=True).open() as session:
        session.declare_subscriber("congestion/**", on_sample)
        print("ready", flush=True)
        sys.stdin.readline()
        with lock:
            print(json.dumps(ages), flush=True)
    return 0


def send(publishers: str, robots: int, ticks: int, period_s: float) -> int:
    """Sender role: ``ticks`` bursts of ``robots`` messages, one every ``period_s``."""
    import zenoh

    from deploy.network import TransportConfig, declare_data_publisher

    drop = zenoh.CongestionControl.DROP
    with TransportConfig(connect=(f"tcp/{RECEIVER}:{PORT}",), insecure=True).open() as session:
        keys = [f"congestion/r{i}/cmd" for i in range(robots)]
        pubs = [declare_data_publisher(session, key, drop, express=publishers == "express") for key in keys]
        time.sleep(1.0)                                      # the receiver's subscription arrives
        next_time = time.monotonic()
        for tick in range(ticks):
            for pub in pubs:
                pub.put(STAMP.pack(time.monotonic_ns(), tick) + PAD)
            next_time += period_s
            time.sleep(max(0.0, next_time - time.monotonic()))
        time.sleep(1.0)                                      # let Zenoh hand over what it holds
    return 0


def one_run(link: ShapedLink, publishers: str, robots: int, ticks: int, period_s: float) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    me = [sys.executable, str(Path(__file__).resolve())]
    receiver = subprocess.Popen(["ip", "netns", "exec", link.receiver, *me, "--role", "receive"],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    try:
        if receiver.stdout.readline().strip() != "ready":
            raise RuntimeError("the receiver did not start")
        subprocess.run(["ip", "netns", "exec", link.sender, *me, "--role", "send", "--publishers",
                        publishers, "--burst", str(robots), "--ticks", str(ticks), "--period-ms",
                        str(period_s * 1e3)], check=True, env=env, timeout=60 + 2 * ticks * period_s)
        time.sleep(DRAIN_S)                      # what the link still holds arrives
        receiver.stdin.write("done\n")
        receiver.stdin.flush()
        ages = np.asarray(json.loads(receiver.stdout.readline()), dtype=float)
    finally:
        receiver.kill()
        receiver.wait()
    pct = (lambda q: round(float(np.percentile(ages, q)), 1)) if len(ages) else (lambda q: None)
    return {"publishers": publishers, "sent": robots * ticks, "received": int(len(ages)),
            "age_ms": {"p50": pct(50), "p99": pct(99), "max": round(float(ages.max()), 1) if len(ages) else None}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rate-kbit", type=positive_int, default=1000, help="link rate [kbit/s] (default 1000)")
    parser.add_argument("--burst", type=positive_int, default=50, metavar="N",
                        help="messages a burst, one per robot (default 50)")
    argtypes.add_deprecated_alias(parser, "--robots", "--burst")
    parser.add_argument("--period-ms", type=float, default=20.0, metavar="MS",
                        help="time between bursts [ms] (default 20)")
    parser.add_argument("--ticks", type=positive_int, default=200, help="bursts a run (default 200)")
    parser.add_argument("--repeats", type=positive_int, default=2, help="runs of each publisher set (default 2)")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    parser.add_argument("--role", choices=["send", "receive"], help=argparse.SUPPRESS)
    parser.add_argument("--publishers", choices=["fleet", "express"], help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if not args.period_ms > 0:
        parser.error(f"--period-ms must be > 0, got {args.period_ms}")
    if args.role == "receive":
        return receive()
    if args.role == "send":
        return send(args.publishers, args.burst, args.ticks, args.period_ms / 1e3)
    if os.geteuid() != 0 or not (shutil.which("ip") and shutil.which("tc")):
        parser.error("needs root and iproute2 (ip netns, tc) to build the shaped link; run it with sudo")
    rows = []
    with ShapedLink(args.rate_kbit) as link:
        for k in range(args.repeats):
            for publishers in ("fleet", "express"):
                progress(f"link_congestion: {publishers} publishers, run {k + 1}/{args.repeats}")
                rows.append(one_run(link, publishers, args.burst, args.ticks, args.period_ms / 1e3))
    document = {"rate_kbit": args.rate_kbit, "robots": args.burst, "period_ms": args.period_ms,
                "ticks": args.ticks, "rows": rows}
    if args.json:
        print_json(document)
        return 0
    print_table(["publishers", "sent", "received", "age p50 [ms]", "p99", "max"],
                [[r["publishers"], r["sent"], r["received"], r["age_ms"]["p50"], r["age_ms"]["p99"],
                  r["age_ms"]["max"]] for r in rows])
    return 0


if __name__ == "__main__":
    sys.exit(main())
