"""A controller that crashes and is restarted by its supervisor, against a fleet that keeps
running on the wall clock (fleet-sim at 20 Hz over Zenoh on 127.0.0.1, safety filter and MEC on).

While no controller runs, every robot brakes on its watchdog and latches (FAULT). The new bridge
process knows nothing of the old one: it waits for every robot's state, re-arms the latched
robots with STOP and drives the fleet home from where it stopped."""

from __future__ import annotations

import json

import pytest

from deploy.network import free_tcp_port
from tests.deploy.test_fleet_sim_bridge import (
    SCRIPTED,
    Proc,
    assert_task_done,
    finish_pair,
    killed_on_exit,
)

pytestmark = pytest.mark.realtime   # real-time fleet-sim and bridge processes

KILL_AT_TICK = 20   # the robots are on their way: the scripted fleet is home at about tick 85


def test_a_bridge_killed_mid_run_and_restarted_brings_the_fleet_home_untouched(tmp_path):
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    bridge_args = ["--fleet", "r", "--scenario", "paper-5", "--connect", endpoint, "--print-ticks", *SCRIPTED]
    with killed_on_exit([]) as procs:
        sim = Proc("fleet-sim", "--fleet", "r", "--scenario", "paper-5", "--rate-hz", "20", "--ticks", "500",
                   "--listen", endpoint, "--report", str(tmp_path / "sim.json"))
        procs.append(sim)
        procs.append(first := Proc("bridge", *bridge_args))
        first.wait_tick(KILL_AT_TICK)
        first.proc.kill()
        first.finish()
        procs.append(second := Proc("bridge", *bridge_args, "--report", str(tmp_path / "bridge.json")))
        finish_pair(sim, second)
    sim, bridge = (json.loads((tmp_path / name).read_text()) for name in ("sim.json", "bridge.json"))
    modes = [t["modes"] for t in sim["trace"]]
    orphaned = [k for k, m in enumerate(modes) if m == ["latched"] * 5]
    assert orphaned, "the robots never latched while no controller ran"
    moving = [max(t["speeds"]) for t in sim["trace"][orphaned[0]:orphaned[-1] + 1]]
    assert max(moving) < 1e-3                       # at rest while latched
    assert bridge["rearms"] >= 5                    # each robot re-armed by the new bridge
    assert any(m == ["run"] * 5 for m in modes[orphaned[-1]:])   # and driven again
    assert_task_done(sim)                           # home, and no contact over the whole run
