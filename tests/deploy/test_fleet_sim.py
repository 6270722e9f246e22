"""deploy.fleet_sim in process over real Zenoh on 127.0.0.1: whom a simulated robot obeys."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zenoh

from deploy.fleet_sim import FleetSim, FleetSimConfig
from deploy.network import FleetKeys, TransportConfig, free_tcp_port
from deploy.wire import CmdMsg, encode
from sim.scenario import make_scenario

pytestmark = pytest.mark.realtime   # fleet-sim on Zenoh sessions


def test_a_robot_obeys_no_command_while_no_controller_token_is_seen():
    """A node that publishes well-formed, fresh commands on r0's key but holds no controller
    liveliness token moves no robot: every command is ignored and counted (before the rule the
    robot drove 0.29 m, into the wall)."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    sim = FleetSim(FleetSimConfig(fleet="nc", scenario=make_scenario("paper-3"), rate_hz=20.0, max_ticks=30,
                                  start_timeout_s=0.1, transport=TransportConfig(listen=(endpoint,))))
    runner = threading.Thread(target=sim.run)
    runner.start()
    with zenoh.open(TransportConfig(connect=(endpoint,)).to_zenoh()) as raw:
        publisher = raw.declare_publisher(FleetKeys("nc").cmd("r0"))
        deadline = time.monotonic() + 10.0
        while not publisher.matching_status and time.monotonic() < deadline:
            time.sleep(0.01)
        assert publisher.matching_status, "fleet-sim never subscribed"
        seq = 0
        while runner.is_alive():
            seq += 1
            publisher.put(encode(CmdMsg(0, 4242, seq, time.monotonic_ns(), (1.0, 0.0), 500)))
            time.sleep(0.02)
    runner.join(timeout=10.0)
    report = sim.summary()
    assert report["rejects"] == {}                          # every command was well formed
    assert report["ignored_without_controller"] >= 10
    assert max(report["speeds"]) == 0.0
    assert np.allclose(report["positions"], sim.world.scenario.starts, atol=0.02)


def test_a_real_time_run_without_a_tick_limit_keeps_a_bounded_trace():
    from deploy.fleet_sim import TRACE_TICKS

    sc = make_scenario("paper-3")
    endless = FleetSim(FleetSimConfig(fleet="tr", scenario=sc, transport=TransportConfig(), rate_hz=20.0))
    for k in range(TRACE_TICKS + 5):
        endless.trace.append({"tick": k})
    assert len(endless.trace) == TRACE_TICKS and endless.trace[0]["tick"] == 5
    bounded = FleetSim(FleetSimConfig(fleet="tr", scenario=sc, transport=TransportConfig(), rate_hz=None))
    assert bounded.trace.maxlen is None              # lock-step (and --ticks) runs keep every tick


def test_fleet_sim_refuses_to_freeze_a_robot_the_team_does_not_have(capsys):
    from stack.cli import main

    assert main(["fleet-sim", "--fleet", "fz", "--scenario", "paper-4", "--model-error", "freeze=4:20"]) == 2
    assert "paper-4 has 4 robots: pick a row in 0..3" in capsys.readouterr().err
