"""router, fleet-sim and bridge as separate processes over mutual TLS, with intruders.

The fleet runs its episode through `formation router` (access control on, every link TLS with
certificates of the fleet CA) while three intruders try to take it over: one holding robot r1's
certificate (a valid one) publishes well-formed, fresh commands for every robot, a forged state
of r0 and an e-stop; one with a self-signed "controller" certificate and one with none try to
link. None gets a message to a node: the fleet completes with nothing rejected (a forged command
with a fresh epoch that reached a robot would have retired the controller's epoch, and every
genuine command after it would read STALE).
"""

from __future__ import annotations

import json
import signal
import time

import pytest
import zenoh

from deploy.certs import CONTROLLER, NodeFiles, make_certs
from deploy.transport import TransportConfig, free_tcp_port
from deploy.wire import CmdMsg, EstopMsg, StateMsg, encode
from tests.deploy.test_fleet_sim_bridge import SCRIPTED, Proc, assert_task_done


@pytest.mark.slow
def test_the_fleet_completes_through_the_router_while_intruders_try_to_command_it(tmp_path):
    certs = tmp_path / "certs"
    assert Proc("certs", "--out", str(certs), "--scenario", "paper-5").finish() == 0
    make_certs(tmp_path / "rogue", [CONTROLLER])
    endpoint = f"tls/127.0.0.1:{free_tcp_port()}"
    tls = ["--certs", str(certs), "--connect", endpoint]
    router = Proc("router", "--fleet", "t", "--scenario", "paper-5", "--certs", str(certs), "--listen", endpoint)
    time.sleep(1.0)
    sim = Proc("fleet-sim", "--fleet", "t", "--scenario", "paper-5", "--lockstep", "--ticks", "150",
               "--report", str(tmp_path / "sim.json"), *tls)
    bridge = Proc("bridge", "--fleet", "t", "--scenario", "paper-5", "--lockstep", "--trace",
                  "--report", str(tmp_path / "bridge.json"), *SCRIPTED, *tls)
    attempts = {"messages": 0, "links_refused": 0}
    try:
        bridge.wait_tick(10)
        r1 = TransportConfig(connect=(endpoint,), mode="client", tls=NodeFiles.in_dir(certs, "r1"))
        with r1.open() as intruder:
            now = time.monotonic_ns()
            for k in range(1, 21):
                for rid in range(5):
                    intruder.put(f"formation/t/robot/r{rid}/cmd",
                                 encode(CmdMsg(rid, 31337, k, now, (1.0, 0.0), 500)))
                intruder.put("formation/t/estop", encode(EstopMsg(31337, k, now, True)))
                intruder.put("formation/t/robot/r0/state",
                             encode(StateMsg(0, 31337, k, now, (0.9, 0.9), (0.0, 0.0))))
                attempts["messages"] += 7
                time.sleep(0.01)
        for folder, plain in ((tmp_path / "rogue", False), (None, True)):
            try:
                if plain:
                    config = zenoh.Config()
                    config.insert_json5("mode", '"client"')
                    config.insert_json5("connect/endpoints", json.dumps([endpoint.replace("tls/", "tcp/")]))
                    zenoh.open(config).close()
                else:
                    TransportConfig(connect=(endpoint,), mode="client",
                                    tls=NodeFiles.in_dir(folder, CONTROLLER)).open().close()
            except zenoh.ZError:
                attempts["links_refused"] += 1
        assert sim.finish() == 0, "".join(sim.stderr)
        bridge.proc.send_signal(signal.SIGTERM)      # the fleet is done: the clean shutdown path
        bridge.finish()
    finally:
        for p in (sim, bridge, router):
            if p.proc.poll() is None:
                p.proc.kill()
    report, controller = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("sim", "bridge"))
    assert attempts == {"messages": 140, "links_refused": 2}
    assert_task_done(report)
    assert report["rejects"] == {} and report["ignored_without_controller"] == 0
    assert controller["rejects"] == {} and controller["estops"] == 0
    assert controller["robot_counts"] == [[0, 5]]
