"""fleet-sim and the bridge on the wall clock over a slow link whose delay jitters: a TCP relay
(:mod:`deploy.delay_relay`) holds every byte 20 +- 10 ms each way between the two Zenoh
peers, so states reach the bridge late and out of step with each other, and commands reach the
robots one or two ticks after the state they answer. Safety filter and MEC on (the defaults)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from deploy.delay_relay import DelayRelay
from deploy.network import free_tcp_port
from tests.deploy.test_fleet_sim_bridge import (
    SCRIPTED,
    TOUCH,
    Proc,
    finish_pair,
    killed_on_exit,
    silent_contacts,
)

pytestmark = pytest.mark.realtime   # real-time fleet-sim and bridge processes

DELAY_S, JITTER_S = 0.02, 0.01
# a robot holds its command through one tick that brings none (the default brakes on the
# first): with 1 its watchdog braked on 23 % of its ticks over this link
ROBOT_GRACE = ["--brake-after-ticks", "2"]


def run_over_relay(tmp_path: Path, sim_args: list[str], bridge_args: list[str]) -> tuple[dict, dict, DelayRelay]:
    """fleet-sim listening on a port, the bridge connecting to it through a DelayRelay."""
    port = free_tcp_port()
    with killed_on_exit([]) as procs:
        sim = Proc("fleet-sim", "--fleet", "j", "--scenario", "paper-5", "--rate-hz", "20", "--listen",
                   f"tcp/127.0.0.1:{port}", "--report", str(tmp_path / "sim.json"), *ROBOT_GRACE, *sim_args)
        procs.append(sim)
        with DelayRelay(port, DELAY_S, JITTER_S) as relay:
            procs.append(bridge := Proc("bridge", "--fleet", "j", "--scenario", "paper-5", "--connect",
                                        f"tcp/127.0.0.1:{relay.port}", "--report", str(tmp_path / "bridge.json"),
                                        *bridge_args))
            finish_pair(sim, bridge)
    return (json.loads((tmp_path / "sim.json").read_text()), json.loads((tmp_path / "bridge.json").read_text()),
            relay)


def test_over_a_jittery_link_the_bridge_measures_the_delay_and_the_fleet_gets_home_untouched(tmp_path):
    """The bridge's round trips (state out, command back, acted on) read the relay's delay:
    p99 49-50 ms without it, 102-108 ms with it, and the filter plans over the larger bound.
    Every robot gets home with no contact: at ticks 103-207 (83-84 without the relay, 81-85 bare
    over it; the filter's allowance for commands whose delay jitters costs the rest).
    ``python bench/jittery_link.py --configs stack,bare --seeds 3``, 2026-12-06."""
    sim, bridge, relay = run_over_relay(tmp_path, ["--ticks", "300"], SCRIPTED)
    assert len(relay.delays) > 1000 and max(relay.delays) > DELAY_S + 0.5 * JITTER_S
    assert bridge["round_trip_ms"]["p99"] > 80.0 and bridge["command_delay_s"] > 0.08
    assert sim["collisions"] == {"robot": 0, "object": 0, "wall": 0}
    assert sim["success"], sim["final_distance"]


@pytest.mark.parametrize("safety", [True, False])
def test_over_a_jittery_link_a_robot_that_falls_silent_in_the_others_path_is_never_touched(tmp_path, safety):
    """r2 leaves the link at tick 60 where the others' lanes pass it later (the lock-stepped
    test of the same name, over the relay): with the filter nobody touches it (closest 163 mm
    in a scratch run) and it stays where it stopped; the same run without filter and MEC drives
    into it (134 ticks of contact) and pushes it 0.1 m."""
    args = SCRIPTED if safety else [*SCRIPTED, "--no-safety", "--no-mec"]
    sim, bridge, _ = run_over_relay(tmp_path, ["--ticks", "200", "--leave", "r2@60"], args)
    assert bridge["round_trip_ms"]["p99"] > 80.0
    touches, closest = silent_contacts(sim, 2)
    if safety:
        assert touches == 0 and closest >= TOUCH, (touches, closest)
        assert sim["collisions"] == {"robot": 0, "object": 0, "wall": 0}
        parked = np.array([t["positions"][2] for t in sim["trace"][70:]])
        assert np.ptp(parked, axis=0).max() < 1e-3      # it stopped where it left, and stayed
    else:
        assert touches > 0 and closest < TOUCH          # and pushed it 0.1 m along

