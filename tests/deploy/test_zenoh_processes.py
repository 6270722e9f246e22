"""Controller in this process, robots in their own processes, over Zenoh on 127.0.0.1."""

from __future__ import annotations

import json
import queue
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from deploy.network import TransportConfig, free_tcp_port
from deploy.transport import FleetLink
from deploy.wire import RobotRegistry

ROBOT_SCRIPT = Path(__file__).with_name("zenoh_robot_proc.py")
sys.path.insert(0, str(ROBOT_SCRIPT.parent))
from zenoh_robot_proc import expected_acceleration  # noqa: E402

pytestmark = pytest.mark.realtime   # Zenoh nodes in processes

FLEET = "procfleet"
ROBOTS = ("r0", "r1")
REGISTRY = RobotRegistry(ROBOTS)
WAIT_S = 15.0  # generous: includes interpreter start-up on a loaded machine


class RobotProcess:
    """A robot process whose JSON stdout lines arrive on a queue."""

    def __init__(self, port: int, robot: str, exchanges: int = 0, lease_ms: int | None = None):
        lease = ["--lease-ms", str(lease_ms)] if lease_ms else []
        self.proc = subprocess.Popen(
            [sys.executable, str(ROBOT_SCRIPT), "--port", str(port), "--fleet", FLEET,
             "--robot", robot, "--robots", ",".join(ROBOTS), "--exchanges", str(exchanges)]
            + lease, stdout=subprocess.PIPE, text=True)
        self.lines: queue.Queue[dict] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(json.loads(line))

    def next_line(self, timeout_s: float = WAIT_S) -> dict:
        line = self.lines.get(timeout=timeout_s)
        assert line["phase"] != "error", line
        return line

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)  # a stopped process must run to die cleanly
            self.proc.kill()
        self.proc.wait(timeout=WAIT_S)


@pytest.fixture
def controller_and_port():
    port = free_tcp_port()
    with FleetLink(FLEET, REGISTRY, TransportConfig(listen=(f"tcp/127.0.0.1:{port}",))) as link:
        yield link, port


def test_state_command_exchange_with_a_robot_process_and_its_death_is_seen(controller_and_port):
    controller, port = controller_and_port
    exchanges = 300
    robot = RobotProcess(port, "r0", exchanges=exchanges)
    try:
        assert controller.wait_for(lambda: "r0" in controller.alive_robots, WAIT_S)
        assert robot.next_line()["phase"] == "ready"
        answered, result = 0, None
        def unanswered_state() -> bool:
            latest = controller.state_of("r0")
            return latest is not None and latest.msg.seq > answered

        while result is None:
            if controller.wait_for(unanswered_state, 0.2):
                state = controller.state_of("r0").msg
                controller.send_command("r0", expected_acceleration(state.position), ttl_ms=100,
                                        state_seq=state.seq)
                answered = state.seq
            try:
                result = robot.lines.get_nowait()
            except queue.Empty:
                assert robot.proc.poll() is None, "robot process ended early"
        assert result["phase"] == "exchanged", result
        assert len(result["rtts_us"]) == exchanges
        assert result["wrong"] == 0 and result["rejects"] == 0
        assert controller.rejects.total == 0
        rtts = np.array(result["rtts_us"])
        print(f"\nloopback state->cmd round trip over {exchanges} exchanges, two processes: "
              f"p50 {np.percentile(rtts, 50):.0f} us, p99 {np.percentile(rtts, 99):.0f} us, "
              f"max {rtts.max():.0f} us")

        controller.pop_events()
        robot.proc.kill()  # SIGKILL: no chance to undeclare its token
        assert controller.wait_for(lambda: "r0" not in controller.alive_robots, WAIT_S)
        assert [(e.robot, e.joined) for e in controller.pop_events()] == [("r0", False)]
    finally:
        robot.kill()


def test_estop_raised_before_a_robot_process_starts_reaches_it(controller_and_port):
    controller, port = controller_and_port
    controller.raise_estop(reason_code=7)
    robot = RobotProcess(port, "r1")
    try:
        assert controller.wait_for(lambda: "r1" in controller.alive_robots, WAIT_S)
        ready = robot.next_line()
        assert ready == {"phase": "ready", "estopped": True, "estop_reason": 7}
        assert [(e.robot, e.joined) for e in controller.pop_events()] == [("r1", True)]
    finally:
        robot.kill()
    assert controller.wait_for(lambda: "r1" not in controller.alive_robots, WAIT_S)


def test_a_frozen_robot_process_leaves_after_its_lease_and_rejoins_when_resumed(
        controller_and_port):
    """A stopped process keeps its TCP link open: only the link lease (1 s here) notices it."""
    controller, port = controller_and_port
    robot = RobotProcess(port, "r0", lease_ms=1000)
    try:
        assert controller.wait_for(lambda: "r0" in controller.alive_robots, WAIT_S)
        robot.next_line()
        controller.pop_events()
        robot.proc.send_signal(signal.SIGSTOP)
        assert controller.wait_for(lambda: "r0" not in controller.alive_robots, WAIT_S)
        robot.proc.send_signal(signal.SIGCONT)
        assert controller.wait_for(lambda: "r0" in controller.alive_robots, WAIT_S)
        assert [(e.robot, e.joined) for e in controller.pop_events()] == [("r0", False),
                                                                          ("r0", True)]
    finally:
        robot.kill()
