"""The bridge's re-arm alarm (deploy/rearm_watch.py): a robot that refuses its commands is named,
counted and kept as an obstacle; a healthy fleet never raises it. Bridge, fleet-sim (real time,
20 Hz) and a forger in this process over real Zenoh on 127.0.0.1."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest

from controllers.scripted import ScriptedController
from deploy.bridge import Bridge
from deploy.fleet_sim import FleetSim, FleetSimConfig, robot_names
from deploy.network import TransportConfig, free_tcp_port
from deploy.rearm_watch import REARM_ALARM_AFTER, RearmWatch
from deploy.wire import CmdMsg, RobotRegistry, StateStatus, encode
from sim.scenario import make_scenario

pytestmark = pytest.mark.realtime   # a bridge and robot links on Zenoh sessions

TICKS = 90   # fleet-sim ticks, 4.5 s at 20 Hz


def run_fleet(during=None) -> tuple[dict, dict, list]:
    """fleet-sim (paper-3, 20 Hz, TICKS ticks) and a bridge; ``during(endpoint)`` runs in a
    thread of its own once the bridge has answered 10 ticks. Returns (fleet-sim report, bridge
    summary, tick records)."""
    scenario = make_scenario("paper-3")
    port = free_tcp_port()
    names = robot_names(3)
    sim = FleetSim(FleetSimConfig(fleet="ra", scenario=scenario, rate_hz=20.0, max_ticks=TICKS,
                                  transport=TransportConfig(listen=(f"tcp/127.0.0.1:{port}",))))
    result: dict = {}
    thread = threading.Thread(target=lambda: result.update(sim.run()))
    thread.start()
    records, helpers = [], []
    bridge = Bridge("ra", RobotRegistry(names), TransportConfig(connect=(f"tcp/127.0.0.1:{port}",)),
                    ScriptedController(scenario), targets=dict(zip(names, scenario.targets, strict=True)),
                    object_pose=np.zeros(3))
    try:
        while thread.is_alive():
            record = bridge.step(timeout_s=0.1)
            if record is not None:
                records.append(record)
            if during is not None and bridge.stats.ticks >= 10:
                helpers.append(threading.Thread(target=during, args=(f"tcp/127.0.0.1:{port}",)))
                helpers[-1].start()
                during = None
    finally:
        for t in (thread, *helpers):
            t.join(timeout=30)
        bridge.close()
    return result, bridge.summary(), records


def forge_one_command(endpoint: str) -> None:
    """One well-formed CMD for r1 with an epoch of its own, stamped now (the clocks are shared
    on loopback): r1 takes it, which retires the bridge's epoch there."""
    config = TransportConfig(connect=(endpoint,))
    with config.open() as session:
        time.sleep(0.3)   # the route to r1's subscriber
        session.put("formation/ra/robot/r1/cmd",
                    encode(CmdMsg(1, 31337, 1, time.monotonic_ns(), (0.0, 0.0), 500)))
        time.sleep(0.1)


def test_a_robot_that_refuses_its_commands_raises_the_alarm_and_becomes_an_obstacle(caplog):
    """Issue #17: after one forged CMD with a fresh epoch r1 reads every genuine CMD as STALE,
    latches (FAULT) and never answers a re-arm. At REARM_ALARM_AFTER re-arms in a row the bridge
    names it, repeats at most once a second, and stops treating it as under control: it leaves
    the rows for the silent obstacles while r0 and r2 drive on."""
    caplog.set_level(logging.WARNING, logger="deploy.rearm_watch")
    sim, summary, records = run_fleet(during=forge_one_command)
    assert sim["rejects"].get("STALE", 0) > 20                  # r1 refused the genuine ones
    modes = [t["modes"] for t in sim["trace"]]
    assert modes[-1] == ["run", "latched", "run"]
    assert summary["rearm_alarms"] == 1 and summary["refusing"] == ["r1"]
    in_a_row = summary["rearms_in_a_row"]
    assert in_a_row["r1"] >= REARM_ALARM_AFTER              # measured 55-65
    assert all(n < REARM_ALARM_AFTER for r, n in in_a_row.items() if r != "r1")   # measured: none
    alarms = [r for r in caplog.records if r.levelno == logging.ERROR]
    assert alarms and "robot r1 refuses its commands" in alarms[0].getMessage()
    assert f"re-armed {REARM_ALARM_AFTER} times in" in alarms[0].getMessage()
    assert "unchanged" in alarms[0].getMessage()                 # its last_cmd_seq stood still
    assert all("robot r1" in r.getMessage() for r in alarms)
    span_s = alarms[-1].created - alarms[0].created
    assert len(alarms) <= 2 + span_s                            # at most once a second
    joined = next(k for k, r in enumerate(records) if r.robots == ("r0", "r1", "r2"))  # all three in
    refusing = [r for r in records[joined:] if "r1" not in r.robots]
    assert refusing and all(r.robots == ("r0", "r2") and "r1" in r.silent for r in refusing)
    first = records.index(refusing[0])
    assert all("r1" not in r.robots for r in records[first:])   # not commanded as a row again
    print(f"re-arms in a row: {summary['rearms_in_a_row']}, alarm lines: {len(alarms)} "
          f"over {span_s:.2f} s, STALE at the robot: {sim['rejects']['STALE']}")


def test_a_healthy_fleet_never_raises_the_alarm(caplog):
    caplog.set_level(logging.WARNING, logger="deploy.rearm_watch")
    sim, summary, _ = run_fleet()
    assert sim["rejects"] == {} and summary["rearm_alarms"] == 0 and summary["refusing"] == []
    assert all(n < REARM_ALARM_AFTER for n in summary["rearms_in_a_row"].values())  # measured: {}
    assert caplog.records == []


def test_the_watch_counts_runs_repeats_at_most_once_per_interval_and_clears_on_an_answer(caplog):
    """The rules alone, on a clock of its own: a STATE without FAULT ends a run; the alarm at the
    threshold, its repeats once per interval, the all-clear."""
    now = [0.0]
    watch = RearmWatch("bridge f", threshold=3, interval_s=1.0, clock=lambda: now[0])
    caplog.set_level(logging.WARNING, logger="deploy.rearm_watch")
    for _ in range(2):
        watch.rearmed("r0", 7)
    watch.state("r0", StateStatus(0))                      # answered: a new run next time
    for k in range(3):
        now[0] = 0.1 * k
        watch.state("r0", StateStatus.FAULT)
        watch.rearmed("r0", 7)
    assert watch.refusing("r0") and watch.alarms == 1
    now[0] = 0.9
    watch.poll()                                           # too soon
    now[0] = 1.3
    watch.poll()
    watch.state("r0", StateStatus.WATCHDOG_BRAKING)        # free of FAULT
    assert not watch.refusing("r0")
    assert [r.getMessage()[:60] for r in caplog.records] == [
        "bridge f: robot r0 refuses its commands: re-armed 3 times in",
        "bridge f: robot r0 refuses its commands: re-armed 3 times in",
        "bridge f: robot r0 answers its commands again (STATE without"]
    assert watch.summary() == {"rearm_alarms": 1, "rearms_in_a_row": {"r0": 3}, "refusing": [],
                               "rearm_alarm_after": 3}
    with pytest.raises(ValueError, match="rearm_alarm_after"):
        RearmWatch("x", threshold=0)
