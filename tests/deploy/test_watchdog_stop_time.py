"""The fleet-sim watchdog stops a fleet within 0.5 s when its controller dies or freezes.

Measured from outside, as an observer on the link would: a Zenoh session of its own (this
test process, scouting off, loopback) subscribes to ``formation/<fleet>/robot/*/state`` of a
real-time fleet-sim process while a controller process (``full_thrust_proc.py``) drives every
robot at the speed limit. Once every robot's published speed is at the limit, the controller
is SIGKILLed (or SIGSTOPped) and the stop time is the publication time (``send_time_ns``, the
fleet's monotonic clock, which is this host's) of the first state from which on every robot's
published speed stays below 1e-3 m/s, minus the moment just before the signal.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from deploy.network import TransportConfig, free_tcp_port
from deploy.wire import MsgType, StateMsg, decode
from sim.scenario import make_scenario

pytestmark = pytest.mark.realtime   # stop times measured on the wall clock

ROOT = Path(__file__).resolve().parents[2]
CONTROLLER = Path(__file__).with_name("full_thrust_proc.py")
WAIT_S = 120.0  # generous: interpreter start-up on a loaded machine
FLEET = "wd"
STOPPED = 1e-3  # m/s
PROMISE_S = 0.5


class StateLog:
    """Every STATE of the fleet as (robot id, send_time_ns, speed), from its own session."""

    def __init__(self, endpoint: str):
        self.session = zenoh.open(TransportConfig(connect=(endpoint,)).to_zenoh())
        self.rows: list[tuple[int, int, float]] = []
        self.lock = threading.Lock()
        self.sub = self.session.declare_subscriber(f"formation/{FLEET}/robot/*/state",
                                                   zenoh.handlers.FifoChannel(100_000))
        threading.Thread(target=self._drain, daemon=True).start()

    def _drain(self) -> None:
        while True:
            try:
                sample = self.sub.handler.recv()
            except zenoh.ZError:
                return
            msg = decode(sample.payload.to_bytes(), MsgType.STATE)
            if isinstance(msg, StateMsg):
                with self.lock:
                    self.rows.append((msg.robot_id, msg.send_time_ns,
                                      float(np.hypot(*msg.velocity))))

    def snapshot(self) -> list[tuple[int, int, float]]:
        with self.lock:
            return list(self.rows)

    def latest_speeds(self, n: int, last: int) -> dict[int, list[float]]:
        out: dict[int, list[float]] = {i: [] for i in range(n)}
        for robot, _, speed in self.snapshot():
            out[robot].append(speed)
        return {r: s[-last:] for r, s in out.items()}

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def stop_time_s(rows: list[tuple[int, int, float]], n: int, t_signal_ns: int) -> float:
    """Latest over robots of the first publication after the signal from which on the
    robot's published speed stays below STOPPED [s after the signal]."""
    worst = 0.0
    for robot in range(n):
        after = [(t, s) for r, t, s in rows if r == robot and t >= t_signal_ns]
        assert after, f"robot {robot} published nothing after the signal"
        assert after[-1][1] < STOPPED, f"robot {robot} still moves at {after[-1][1]} m/s"
        first = len(after)
        while first > 0 and after[first - 1][1] < STOPPED:
            first -= 1
        worst = max(worst, (after[first][0] - t_signal_ns) / 1e9)
    return worst


def _spawn(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def measure_stop(tmp_path: Path, sig: signal.Signals, sim_args: tuple[str, ...] = ()) -> dict:
    """Drive paper-5 at the speed limit, send ``sig`` to the controller, measure the stop."""
    n = make_scenario("paper-5").num_robots
    limit = make_scenario("paper-5").dynamics.speed_limit
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    report = tmp_path / f"sim-{sig.name}.json"
    sim = _spawn([sys.executable, "-m", "stack.cli", "fleet-sim", "--fleet", FLEET,
                  "--scenario", "paper-5", "--rate-hz", "20", "--listen", endpoint,
                  "--ticks", "2000", "--report", str(report), *sim_args])
    log = controller = None
    try:
        log = StateLog(endpoint)
        deadline = time.monotonic() + WAIT_S
        while len(list(log.session.info.peers_zid())) < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        controller = _spawn([sys.executable, str(CONTROLLER), "--connect", endpoint,
                             "--fleet", FLEET])
        while time.monotonic() < deadline:   # every robot at the limit in its last 2 states
            speeds = log.latest_speeds(n, 2)
            if all(len(s) == 2 and min(s) >= limit - 1e-9 for s in speeds.values()):
                break
            assert sim.poll() is None and controller.poll() is None, "a process ended early"
            time.sleep(0.005)
        else:
            pytest.fail("the fleet never reached the speed limit")
        t_signal = time.monotonic_ns()
        os.kill(controller.pid, sig)
        time.sleep(1.5)   # long past the promise: every later state must be at rest
        rows = log.snapshot()
        sim.send_signal(signal.SIGTERM)
        assert sim.wait(timeout=WAIT_S) == 0, sim.stderr.read()
    finally:
        if controller is not None and controller.poll() is None:
            controller.send_signal(signal.SIGCONT)
            controller.kill()
            controller.wait(timeout=WAIT_S)
        if sim.poll() is None:
            sim.kill()
        if log is not None:
            log.close()
    at_signal = [s for r, t, s in rows if t < t_signal][-n:]
    summary = json.loads(report.read_text())
    return {"stop_s": stop_time_s(rows, n, t_signal), "speeds_at_signal": at_signal,
            "collisions": summary["collisions"], "modes": summary["trace"][-1]["modes"]}


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSTOP], ids=["killed", "frozen"])
def test_every_robot_is_at_rest_within_half_a_second_of_losing_its_controller(tmp_path, sig):
    result = measure_stop(tmp_path, sig)
    print(f"\ncontroller {sig.name} at the speed limit: every published speed < {STOPPED} m/s "
          f"after {result['stop_s']:.3f} s")
    assert min(result["speeds_at_signal"]) >= 0.4 - 1e-9   # at the speed limit when it died
    assert result["collisions"] == {"robot": 0, "object": 0, "wall": 0}  # braked, not stopped
    assert result["stop_s"] < PROMISE_S
    assert result["modes"] == ["latched"] * 5   # and then the watchdog latch holds them
