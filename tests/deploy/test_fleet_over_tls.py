"""router, fleet-sim and bridge as separate processes over mutual TLS, with intruders; on
127.0.0.1, and across network namespaces (one per host) joined by veth pairs.

The fleet runs its episode through `formation router` (access control on, every link TLS with
certificates of the fleet CA) while the intruders of tests/deploy/intruder_proc.py try to take it
over: one holding robot r1's (valid) certificate publishes well-formed, fresh commands for every
robot, an e-stop and a forged state of r0; one with a self-signed "controller" certificate and one
with none try to link. None gets a message to a node: the fleet completes with nothing rejected
(a forged command with a fresh epoch that reached a robot would have retired the controller's
epoch, and every genuine command after it would read STALE; a forged e-stop would have stopped
the fleet). The router's exit report counts what it refused: the intruder's puts under r1, the two
links by reason, nothing of the controller or the fleet.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from deploy.certs import CONTROLLER, make_certs
from deploy.network import free_tcp_port
from tests.deploy.intruder_proc import intrude
from tests.deploy.test_fleet_sim_bridge import ROOT, SCRIPTED, Proc, assert_task_done

pytestmark = pytest.mark.realtime   # router, fleet-sim and bridge processes over TLS

ROBOTS = 5


def run_fleet(tmp_path: Path, listen: str, sim_to: str, bridge_to: str, intruders, prefix=None) -> tuple:
    """Router (listening on ``listen``), fleet-sim and bridge (connecting to ``sim_to`` and
    ``bridge_to``), each under ``prefix(role)`` (e.g. ``ip netns exec``); ``intruders()`` runs
    once the bridge has answered 10 ticks. Returns (fleet-sim report, bridge report, router
    report, attempts)."""
    certs = tmp_path / "certs"
    wrap = prefix or (lambda role: ())
    router = Proc("router", "--fleet", "t", "--scenario", "paper-5", "--certs", str(certs),
                  "--listen", listen, "--report", str(tmp_path / "router.json"), prefix=wrap("router"))
    time.sleep(1.0)
    sim = Proc("fleet-sim", "--fleet", "t", "--scenario", "paper-5", "--lockstep", "--ticks", "150",
               "--report", str(tmp_path / "sim.json"), "--certs", str(certs), "--connect", sim_to,
               prefix=wrap("sim"))
    bridge = Proc("bridge", "--fleet", "t", "--scenario", "paper-5", "--lockstep", "--print-ticks",
                  "--report", str(tmp_path / "bridge.json"), *SCRIPTED, "--certs", str(certs),
                  "--connect", bridge_to, prefix=wrap("ctrl"))
    try:
        bridge.wait_tick(10)
        attempts = intruders()
        assert sim.finish() == 0, "".join(sim.stderr)
        bridge.proc.send_signal(signal.SIGTERM)      # the fleet is done: the clean shutdown path
        bridge.finish()
        router.proc.send_signal(signal.SIGTERM)
        assert router.finish() == 0, "".join(router.stderr)
    finally:
        for p in (sim, bridge, router):
            if p.proc.poll() is None:
                p.proc.send_signal(signal.SIGTERM)
                try:
                    p.proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    p.proc.kill()
    reports = [json.loads((tmp_path / f"{n}.json").read_text()) for n in ("sim", "bridge", "router")]
    return (*reports, attempts)


def check(report: dict, controller: dict, router: dict, attempts: dict) -> None:
    assert attempts == {"messages": 20 * (ROBOTS + 2), "links_refused": 2}
    assert_task_done(report)
    assert report["rejects"] == {} and report["ignored_without_controller"] == 0
    assert controller["rejects"] == {} and controller["estops"] == 0
    assert controller["robot_counts"] == [[0, ROBOTS]]
    assert controller["rearm_alarms"] == 0 and controller["refusing"] == []
    assert router["counting"] and list(router["denied"]) == ["r1"]   # the intruder, no one else
    denied = router["denied"]["r1"]     # measured: all 140, 20 on each key
    keys = [f"robot/r{i}/cmd" for i in range(ROBOTS)] + ["estop", "robot/r0/state"]
    assert sorted(denied) == sorted(f"Put formation/t/{k}" for k in keys)
    assert sum(denied.values()) <= attempts["messages"]
    assert sum(router["refused_links"].values()) == 2


def make_fleet_certs(tmp_path: Path, *hosts: str) -> None:
    host_args = [a for h in hosts for a in ("--host", h)]
    assert Proc("certs", "--out", str(tmp_path / "certs"), "--scenario", "paper-5", *host_args).finish() == 0
    make_certs(tmp_path / "rogue", [CONTROLLER])


@pytest.mark.slow
def test_the_fleet_completes_through_the_router_while_intruders_try_to_command_it(tmp_path):
    make_fleet_certs(tmp_path)
    endpoint = f"tls/127.0.0.1:{free_tcp_port()}"
    *reports, attempts = run_fleet(
        tmp_path, endpoint, endpoint, endpoint,
        lambda: intrude("t", ROBOTS, endpoint, str(tmp_path / "certs"), str(tmp_path / "rogue")))
    check(*reports, attempts)


# one namespace per host, each joined to the router's by a veth pair (a /30 of its own)
HOSTS = {"sim": 1, "ctrl": 2, "intruder": 3}


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=10)


def _namespaces_allowed() -> str | None:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        return "needs root and iproute2 (ip netns) to build network namespaces"
    probe = f"fsprobe{os.getpid()}"
    try:
        _ip("netns", "add", probe)
        _ip("netns", "del", probe)
    except (subprocess.CalledProcessError, OSError) as err:
        return f"network namespaces are not allowed here: {err}"
    return None


@pytest.fixture
def hosts():
    reason = _namespaces_allowed()
    if reason:
        pytest.skip(reason)
    tag = f"fs{os.getpid() % 10000}"
    names = {role: f"{tag}{role}" for role in ("router", *HOSTS)}
    try:
        for ns in names.values():
            _ip("netns", "add", ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        for role, k in HOSTS.items():
            a, b = f"{tag}r{k}", f"{tag}h{k}"
            _ip("link", "add", a, "netns", names["router"], "type", "veth", "peer", "name", b,
                "netns", names[role])
            _ip("-n", names["router"], "addr", "add", f"10.77.{k}.1/30", "dev", a)
            _ip("-n", names[role], "addr", "add", f"10.77.{k}.2/30", "dev", b)
            _ip("-n", names["router"], "link", "set", a, "up")
            _ip("-n", names[role], "link", "set", b, "up")
        yield names
    finally:
        for ns in names.values():
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)


@pytest.mark.slow
def test_across_hosts_the_fleet_completes_through_the_router_and_intruders_move_nothing(tmp_path, hosts):
    """Router, fleet-sim, bridge and the intruders each in a network namespace of its own (a host):
    every byte between them crosses a veth pair and the router, on addresses this test made."""
    router_ips = [f"10.77.{k}.1" for k in HOSTS.values()]
    make_fleet_certs(tmp_path, *router_ips)
    port = 7447
    endpoint = {role: f"tls/10.77.{k}.1:{port}" for role, k in HOSTS.items()}

    def intruders() -> dict:
        out = subprocess.run(["ip", "netns", "exec", hosts["intruder"], sys.executable,
                              str(ROOT / "tests" / "deploy" / "intruder_proc.py"), "--fleet", "t",
                              "--robots", str(ROBOTS), "--endpoint", endpoint["intruder"],
                              "--certs", str(tmp_path / "certs"), "--rogue", str(tmp_path / "rogue")],
                             cwd=ROOT, capture_output=True, text=True, timeout=120,
                             env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert out.returncode == 0, out.stderr
        return json.loads(out.stdout.strip().splitlines()[-1])

    *reports, attempts = run_fleet(
        tmp_path, f"tls/0.0.0.0:{port}", endpoint["sim"], endpoint["ctrl"], intruders,
        prefix=lambda role: ("ip", "netns", "exec", hosts[role]))
    check(*reports, attempts)
