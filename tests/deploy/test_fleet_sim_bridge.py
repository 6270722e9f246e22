"""fleet-sim and bridge as separate processes over Zenoh on 127.0.0.1 (lock-step, scouting off)."""

from __future__ import annotations

import contextlib
import json
import math
import queue
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
from deploy.wire import CMD_BODY, HEADER, MAGIC, STATE_BODY, WIRE_VERSION, MsgType
from sim.scenario import make_scenario

pytestmark = pytest.mark.realtime   # fleet-sim and bridge processes at 20 Hz

ROOT = Path(__file__).resolve().parents[2]
WAIT_S = 120.0  # generous: includes interpreter start-up on a loaded machine
SCRIPTED = ["--policy", "scripted"]  # safety filter and MEC on (the defaults)


class Proc:
    """A `formation` subcommand in its own process; stdout lines arrive on a queue."""

    def __init__(self, *args: str, prefix: tuple[str, ...] = ()):
        """``prefix``: a command to run it under, e.g. ``("ip", "netns", "exec", NS)``."""
        self.proc = subprocess.Popen([*prefix, sys.executable, "-m", "stack.cli", *args], cwd=ROOT,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: queue.Queue[str] = queue.Queue()
        self.stderr: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()
        threading.Thread(target=lambda: self.stderr.extend(self.proc.stderr), daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line)

    def wait_tick(self, tick: int) -> None:
        """Block until the bridge (run with --print-ticks) has answered ``tick``."""
        while True:
            line = self.lines.get(timeout=WAIT_S)
            if json.loads(line).get("tick", -1) >= tick:
                return

    def finish(self) -> int:
        try:
            return self.proc.wait(timeout=WAIT_S)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()


def run_pair(tmp_path: Path, sim_args: list[str], bridge_args: list[str],
             during=None) -> tuple[dict, dict | None, Proc]:
    """Run fleet-sim (listening on ``port``) and a bridge connecting to it; ``during(bridge,
    port, bridge_port)`` runs meanwhile (the bridge also listens on ``bridge_port``)."""
    port, bridge_port = free_tcp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    sim = Proc("fleet-sim", "--fleet", "t", "--scenario", "paper-5", "--lockstep",
               "--listen", endpoint, "--report", str(tmp_path / "sim.json"), *sim_args)
    bridge = Proc("bridge", "--fleet", "t", "--scenario", "paper-5", "--connect", endpoint,
                  "--listen", f"tcp/127.0.0.1:{bridge_port}", "--print-ticks", "--lockstep",
                  "--report", str(tmp_path / "bridge.json"), *bridge_args)
    try:
        if during is not None:
            during(bridge, port, bridge_port)
        assert sim.finish() == 0, "".join(sim.stderr)
        if bridge.proc.poll() is None:
            bridge.proc.send_signal(signal.SIGTERM)  # clean shutdown path
        bridge.finish()
    finally:
        for p in (sim, bridge):
            if p.proc.poll() is None:
                p.proc.kill()
    sim_report = json.loads((tmp_path / "sim.json").read_text())
    bridge_path = tmp_path / "bridge.json"
    bridge_report = json.loads(bridge_path.read_text()) if bridge_path.exists() else None
    return sim_report, bridge_report, bridge


@contextlib.contextmanager
def killed_on_exit(procs: list[Proc]):
    """Kill whatever of ``procs`` (a list that may grow inside the block) still runs at the
    end, stopped ones included."""
    try:
        yield procs
    finally:
        for p in procs:
            if p.proc.poll() is None:
                p.proc.send_signal(signal.SIGCONT)
                p.proc.kill()


def finish_pair(sim: Proc, bridge: Proc) -> None:
    """fleet-sim run to its end (exit 0), then the bridge stopped the clean way (SIGTERM, exit 0)."""
    assert sim.finish() == 0, "".join(sim.stderr)
    bridge.proc.send_signal(signal.SIGTERM)
    assert bridge.finish() == 0, "".join(bridge.stderr)


def assert_task_done(report: dict) -> None:
    assert report["collisions"] == {"robot": 0, "object": 0, "wall": 0}
    assert report["success"], report["final_distance"]


def offline_ticks(report: dict, robot: int) -> list[int]:
    return [t["tick"] for t in report["trace"] if t["modes"][robot] == "offline"]


def silent_contacts(report: dict, robot: int) -> tuple[int, float]:
    """While ``robot`` is off the link: (ticks on which it touches another robot, smallest
    distance between its centre and another's [m]), from fleet-sim's true positions."""
    ticks = offline_ticks(report, robot)
    assert ticks, f"robot {robot} never went offline"
    pos = np.array([report["trace"][t]["positions"] for t in ticks])          # (T, N, 2)
    contact = np.array([report["trace"][t]["contacts"] for t in ticks])[:, robot, 0]
    gaps = np.linalg.norm(pos - pos[:, robot:robot + 1], axis=2)
    gaps[:, robot] = np.inf
    return int(contact.sum()), float(gaps.min())


TOUCH = 2 * make_scenario("paper-5").robot_radius  # centre distance at contact [m]
SILENT_IN_THE_WAY = ["--leave", "r2@60"]  # r2 stops where r3 and r4 pass on their lanes later


def test_scripted_controller_brings_five_robots_home_without_collision(tmp_path):
    sim, bridge, proc = run_pair(tmp_path, ["--ticks", "150"], SCRIPTED)
    assert_task_done(sim)
    assert sim["rejects"] == {} and bridge["rejects"] == {}
    assert bridge["robot_counts"] == [[0, 5]]
    assert bridge["estops"] == 0 and bridge["controller_faults"] == 0
    assert sim["lossless"] and bridge["lossless"] and bridge["lockstep"]   # both lock-stepped
    assert proc.proc.returncode == 0  # SIGTERM: loop stopped, session closed, report written
    running = [t for t in sim["trace"] if t["modes"] == ["run"] * 5]
    assert len(running) >= 100  # commands arrived in lock-step nearly every tick


@pytest.mark.slow
def test_control_stack_with_safety_and_mec_over_zenoh(tmp_path):
    sim, bridge, _ = run_pair(tmp_path, ["--ticks", "150", "--model-error", '{"gain": 0.8}'],
                              ["--policy", "scripted"])
    assert_task_done(sim)
    assert bridge["controller_faults"] == 0


def test_task_completes_with_a_fifth_of_the_commands_dropped(tmp_path):
    # A dropped command costs its robot one tick of braking (its watchdog) where the filter
    # counted on the command: the default 150 ms bound covers it. (Told a 50 ms bound, as the
    # link's delay alone would suggest, the filter lets two robots touch on 4 ticks of this
    # seed: it assumes every robot executes its command, and a braking one does not give way.)
    sim, _, _ = run_pair(tmp_path, ["--ticks", "240", "--drop-commands", "0.2"], SCRIPTED)
    total = 240 * 5
    assert 0.1 * total < sim["dropped_commands"] < 0.3 * total
    assert_task_done(sim)


def test_sigkill_of_the_bridge_stops_every_robot_within_half_a_second(tmp_path):
    def kill_mid_run(bridge: Proc, port: int, bridge_port: int) -> None:
        bridge.wait_tick(20)
        bridge.proc.kill()

    sim, bridge, _ = run_pair(tmp_path, ["--ticks", "60", "--lockstep-timeout", "0.05"],
                              SCRIPTED, during=kill_mid_run)
    assert bridge is None  # killed: no report
    trace = sim["trace"]
    last_run = max(t["tick"] for t in trace if "run" in t["modes"])
    # moving when the controller died (the tick after is already braking at 0.05 m/s a tick:
    # measured there, 0.094 against 0.1 failed a run whose kill landed a tick later)
    assert max(trace[last_run]["speeds"]) > 0.1
    half_second = last_run + 1 + math.ceil(0.5 / 0.05)
    assert all(m in ("watchdog", "latched") for m in trace[last_run + 3]["modes"])
    assert max(trace[half_second]["speeds"]) < 1e-3
    assert trace[-1]["modes"] == ["latched"] * 5
    assert sim["collisions"] == {"robot": 0, "object": 0, "wall": 0}


def test_robots_leaving_and_rejoining_change_n_and_the_task_completes(tmp_path):
    sim, bridge, _ = run_pair(
        tmp_path, ["--ticks", "200", "--leave", "r4@30", "--join", "r4@50", "--leave", "r0@150"],
        [*SCRIPTED, "--record", str(tmp_path / "rec"), "--record-ticks", "120"])
    counts = [n for _, n in bridge["robot_counts"]]
    assert counts == [5, 4, 5, 4]
    assert bridge["rearms"] >= 1  # r4 came back latched and was re-armed with STOP
    modes = [t["modes"][4] for t in sim["trace"]]
    assert modes[35] == "offline" and "latched" in modes[50:53]
    assert silent_contacts(sim, 4)[0] == 0
    assert_task_done(sim)
    assert_recorded(tmp_path / "rec", sim, bridge["ticks"], joins=(50, 51))


def assert_recorded(folder: Path, sim: dict, ticks: int, joins: tuple[int, ...] = ()) -> None:
    """The bridge's records (--record, 120 ticks a file) hold every tick it answered, each robot in
    its column, absent while off the link, where fleet-sim reported it at that time. At a tick of
    ``joins`` (the fleet tick a robot's link reopened, and the next) the bridge may answer the others before it
    hears the rejoining robot's liveliness token, which travels apart from the states (1 run in
    16, before and after 2026-12-06's gather change), so a robot may still be absent there. A
    burst whose last state came after the bridge's gather (a loaded machine) is answered in two
    parts at the same time: in the first, a robot is absent or at its previous tick's position."""
    from stack.recorder import load_record

    first, second = (load_record(folder / f"record_0000{k}.npz") for k in (0, 1))
    assert (first.steps, first.meta["closed_by"], second.meta["closed_by"]) == (120, "chunk", "exit")
    assert first.steps + second.steps == ticks and not (folder / "record_00002.npz").exists()
    trace = {round(t["t"], 6): t for t in sim["trace"]}
    for rec in (first, second):
        assert list(rec.ids) == ["r0", "r1", "r2", "r3", "r4"] and not rec.contacts.any()
        for k in range(rec.steps):
            seen = trace[round(float(rec.time[k]), 6)]
            offline = [m == "offline" for m in seen["modes"]]
            part = k + 1 < rec.steps and rec.time[k + 1] == rec.time[k]   # a burst answered in two parts
            if seen["tick"] in joins or part:
                offline = [o or not p for o, p in zip(offline, rec.present[k], strict=True)]
            np.testing.assert_array_equal(rec.present[k], np.logical_not(offline), err_msg=f"fleet tick {seen['tick']}")
            online = ~np.array(offline)
            off = np.abs(rec.measured[k] - np.array(seen["positions"])).max(1)[online]
            if part:    # a robot not in the first part is answered on its previous tick's state
                before = sim["trace"][seen["tick"] - 1]["positions"]
                off = np.minimum(off, np.abs(rec.measured[k] - np.array(before)).max(1)[online])
            assert off.max() <= 2e-6, (f"fleet tick {seen['tick']}, record row {k}: positions off "
                                       f"the fleet's by {np.round(off * 1e3, 3)} mm")
    assert not first.present[35, 4] and not second.present[-1, 0]


def test_a_lockstep_run_with_a_silent_robot_repeats_exactly(tmp_path):
    """Ages, silences and round trips count fleet ticks under --lockstep, so the same run gives
    the same trace however busy the machine (on the wall clock it diverged after the leave)."""
    runs = []
    for k in range(2):
        (tmp_path / str(k)).mkdir()
        runs.append(run_pair(tmp_path / str(k), ["--ticks", "60", "--leave", "r4@20"], SCRIPTED)[0])
    assert runs[0]["trace"][21]["modes"][4] == "offline"
    assert runs[0]["trace"] == runs[1]["trace"]


def test_a_robot_that_falls_silent_in_the_others_path_is_never_touched(tmp_path):
    sim, bridge, _ = run_pair(tmp_path, ["--ticks", "200", *SILENT_IN_THE_WAY], SCRIPTED)
    assert [n for _, n in bridge["robot_counts"]] == [5, 4]
    assert [m for _, m in bridge["silent_counts"]] == [1]      # passed on as an obstacle
    ticks = offline_ticks(sim, 2)
    assert ticks[0] == 60 and len(ticks) == 140
    parked = np.array([sim["trace"][t]["positions"][2] for t in ticks[10:]])
    assert np.ptp(parked, axis=0).max() < 1e-3     # braked, and stays where it stopped
    touches, closest = silent_contacts(sim, 2)
    assert touches == 0 and closest >= TOUCH, (touches, closest)
    assert sim["collisions"] == {"robot": 0, "object": 0, "wall": 0}
    # r4 stands 58 mm from its target, held off by r2's bound: the operator is told, and by whom
    holds = bridge["holds"]
    assert holds and {h["robot"] for h in holds} == {"r4"}, holds
    assert all(h["not_listening"][0][0] == "r2" and h["target_m"] > 0.05 for h in holds)


def test_a_tracker_that_identifies_the_robots_never_holds_them_and_a_silent_one_stays_untouched(tmp_path):
    """fleet-sim's tracker identifying every robot (flag ROBOT over Zenoh, 5 mm, 2 cm/s): while
    all report, the lock-stepped run is the one without a tracker, tick for tick (a robot's own
    sighting never holds it; taken for an obstacle, it would); with r2 silent in the others'
    path, its sightings bound it once at rest and nobody touches it."""
    runs = []
    for k, extra in enumerate(([], ["--track-robots"])):
        (tmp_path / str(k)).mkdir()
        runs.append(run_pair(tmp_path / str(k), ["--ticks", "80", *extra], SCRIPTED))
    assert [e["positions"] for e in runs[0][0]["trace"]] == [e["positions"] for e in runs[1][0]["trace"]]
    assert runs[1][1]["sightings"]["accepted"] == 5 * 80 and runs[1][1]["rejects"] == {}
    sim, bridge, _ = run_pair(tmp_path, ["--ticks", "200", *SILENT_IN_THE_WAY, "--track-robots"], SCRIPTED)
    assert [m for _, m in bridge["silent_counts"]] == [1]
    touches, closest = silent_contacts(sim, 2)
    assert touches == 0 and closest >= TOUCH, (touches, closest)
    assert sim["collisions"] == {"robot": 0, "object": 0, "wall": 0}


def test_without_the_filter_the_others_do_run_into_the_silent_robot(tmp_path):
    """The comparison that gives the test above its teeth: the same run, unfiltered."""
    sim, _, _ = run_pair(tmp_path, ["--ticks", "200", *SILENT_IN_THE_WAY],
                         ["--policy", "scripted", "--no-safety", "--no-mec"])
    touches, closest = silent_contacts(sim, 2)
    assert touches > 0 and closest < TOUCH


BOX = ["--intruder", "radius=0.05,x=0.5,y=0.8"]   # stands on the top lane, 10 cm above the object
WALKERS = ["--intruder", "radius=0.05,x=0.5,y=1.05,vy=-0.2,leave=110",   # down across both outer lanes
           "--intruder", "radius=0.04,x=-0.05,y=0.3,vx=0.15,max_speed=0.3"]  # along the bottom lane, head-on
IMPERFECT_LINK = ["--model-error", "delay_ticks=2,position_noise_std=0.005,velocity_noise_std=0.01"]


def test_robots_keep_clear_of_a_box_the_tracker_reports_and_still_arrive(tmp_path):
    """Two ticks of command delay, 5 mm and 1 cm/s of noise, filter + MEC on: every robot stays
    more than 5 mm from the box (11.9 mm when written), the task completes, and the operator is
    told who held r2 up."""
    sim, bridge, _ = run_pair(tmp_path, ["--ticks", "128", *BOX, *IMPERFECT_LINK], SCRIPTED)
    assert sim["intruders"]["drive_in_ticks"] == 0 and sim["intruders"]["min_gap_mm"] > 5.0, sim["intruders"]
    assert_task_done(sim)
    assert bridge["sightings"] == {"accepted": 128, "gone": 0, "in_view": ["#0"]}
    assert any(h["not_listening"][0][0] == "obstacle #0" for h in bridge["holds"]), bridge["holds"]


def test_robots_keep_clear_of_walkers_the_tracker_reports(tmp_path):
    """One walker crosses both outer lanes at 0.2 m/s and leaves (GONE), one walks the bottom
    lane head-on at 0.15 m/s (reported at up to 0.3): no robot comes within 5 mm of either."""
    sim, bridge, _ = run_pair(tmp_path, ["--ticks", "128", *WALKERS, *IMPERFECT_LINK], SCRIPTED)
    assert sim["intruders"]["drive_in_ticks"] == 0 and sim["intruders"]["min_gap_mm"] > 5.0, sim["intruders"]
    assert sim["collisions"] == {"robot": 0, "object": 0, "wall": 0}
    assert bridge["sightings"] == {"accepted": 128 + 111, "gone": 1, "in_view": ["#1"]}


def test_without_the_filter_the_robots_drive_into_what_the_tracker_reports(tmp_path):
    """The teeth of the two tests above: the same link and intruders, unfiltered."""
    sim, _, _ = run_pair(tmp_path, ["--ticks", "128", *BOX, *WALKERS, *IMPERFECT_LINK],
                         ["--policy", "scripted", "--no-safety", "--no-mec"])
    assert sim["intruders"]["drive_in_ticks"] > 0 and sim["intruders"]["min_gap_mm"] < -10.0, sim["intruders"]


def test_a_robot_that_leaves_in_the_others_path_and_rejoins_is_never_touched(tmp_path):
    # the rejoined link's first answer needs its subscribers declared and the controller's token
    # heard: 0.25 s (the default wait) was once too short on a loaded 2-core machine, and the
    # re-arm then came a tick late; the wait is not what this test measures
    sim, bridge, _ = run_pair(tmp_path, ["--ticks", "300", *SILENT_IN_THE_WAY, "--join", "r2@100",
                                         "--lockstep-timeout", "2"], SCRIPTED)
    assert [n for _, n in bridge["robot_counts"]] == [5, 4, 5]
    assert offline_ticks(sim, 2) == list(range(60, 100))
    touches, closest = silent_contacts(sim, 2)
    assert touches == 0 and closest >= TOUCH, (touches, closest)
    modes = [t["applied"][2] for t in sim["trace"]]
    assert modes[100] == "stop" and modes[101] == "run"   # re-armed (FAULT -> STOP) and driving
    # the rejoined link heard the controller's token before its first answer was taken
    assert sim["ignored_without_controller"] == 0 and sim["lockstep_timeouts"] == 0
    assert bridge["rearms"] >= 1
    path = np.array([t["positions"][2] for t in sim["trace"][100:]])
    assert np.linalg.norm(path - path[0], axis=1).max() > 0.01   # it moves again
    assert sim["collisions"] == {"robot": 0, "object": 0, "wall": 0}


def _cmd_bytes(robot_id: int, seq: int, acc=(0.0, 0.0), ttl_ms: int = 100, sent_ns: int = 1) -> bytes:
    return (HEADER.pack(MAGIC, WIRE_VERSION, int(MsgType.CMD), robot_id, 0, 77, seq, sent_ns)
            + CMD_BODY.pack(*acc, 0, ttl_ms, 0))


def test_bad_messages_are_rejected_and_counted_while_the_nodes_keep_running(tmp_path):
    # The injector listens and both nodes connect to it as they start, so its links are up
    # before the run: a session opened mid-run may link after a 150-tick lock-step run ended.
    inject_endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with zenoh.open(TransportConfig(listen=(inject_endpoint,)).to_zenoh()) as session:
        def inject(bridge: Proc, port: int, bridge_port: int) -> None:
            # messages put before the links to both nodes are up are dropped: wait for them
            deadline = time.monotonic() + WAIT_S
            while len(list(session.info.peers_zid())) < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert len(list(session.info.peers_zid())) >= 2, "injector not linked to both nodes"
            bridge.wait_tick(10)   # running: every declaration has travelled
            cmd_r1 = "formation/t/robot/r1/cmd"
            bad_cmds = [b"garbage", _cmd_bytes(1, 5, (math.nan, 0.0)),  # NON_FINITE
                        _cmd_bytes(3, 6),                             # ROBOT_MISMATCH
                        _cmd_bytes(1, 7, ttl_ms=0),                   # BAD_TTL
                        b"XX" + _cmd_bytes(1, 8)[2:]]                 # BAD_MAGIC
            # one host, one clock: a new epoch dated 1000 s ahead would otherwise take the
            # stream over, and the genuine robot's (or controller's) messages become STALE
            future = time.monotonic_ns() + 10**12
            bad_cmds.append(_cmd_bytes(1, 9, (0.3, 0.0), sent_ns=future))  # FROM_FUTURE
            for payload in bad_cmds:
                session.put(cmd_r1, payload)
            state = (HEADER.pack(MAGIC, WIRE_VERSION, int(MsgType.STATE), 9, 0, 5, 1, 1)
                     + STATE_BODY.pack(0.5, 0.5, 0.0, 0.0, 0, 0))
            session.put("formation/t/robot/r9/state", state)  # not a robot of this fleet
            session.put("formation/t/robot/r2/state", state[:40])  # truncated
            forged = (HEADER.pack(MAGIC, WIRE_VERSION, int(MsgType.STATE), 2, 0, 5, 10**6, future)
                      + STATE_BODY.pack(0.9, 0.9, 0.0, 0.0, 0, 0))
            session.put("formation/t/robot/r2/state", forged)  # FROM_FUTURE
            bridge.wait_tick(20)

        connect = ["--connect", inject_endpoint]
        sim, bridge, _ = run_pair(tmp_path, ["--ticks", "150", *connect], SCRIPTED + connect,
                                  during=inject)
    assert sim["rejects"] == {"BAD_SIZE": 1, "BAD_MAGIC": 1, "BAD_TTL": 1, "NON_FINITE": 1,
                              "ROBOT_MISMATCH": 1, "FROM_FUTURE": 1}
    assert sim["shared_clock"] and bridge["shared_clock"]       # every endpoint on loopback
    assert_task_done(sim)
    assert bridge["rejects"] == {"BAD_SIZE": 1, "UNKNOWN_ROBOT": 1, "FROM_FUTURE": 1}
    assert bridge["ticks"] >= 140 and bridge["estops"] == 0


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["torchscript", "onnx", "npz"])
def test_bridge_runs_an_exported_policy_through_the_control_stack(tmp_path, fmt):
    import torch

    from controllers.policy import ActorConfig, build_actor
    from deploy.export import export_policy

    torch.manual_seed(0)
    actor = build_actor(ActorConfig(embed_dim=32, velocity_damping=2.0), 5)
    path = export_policy(actor, tmp_path / "policy", dt=0.05, trained_robots=5, formats=(fmt,))[0].path
    sim, bridge, _ = run_pair(tmp_path, ["--ticks", "30"], ["--policy", str(path)])
    assert bridge["controller_faults"] == 0 and bridge["ticks"] >= 29
    assert bridge["heap_frozen"] > 50_000 and sim["heap_frozen"] > 50_000   # no ~0.1 s full collection mid-run
    assert sum(t["modes"] == ["run"] * 5 for t in sim["trace"]) >= 25
    assert sim["collisions"] == {"robot": 0, "object": 0, "wall": 0}


def test_with_a_playout_buffer_each_command_acts_two_ticks_after_its_state(tmp_path):
    """fleet-sim --playout-ticks 2: every robot acts on the command answering its state of two
    ticks before, so the bridge measures a steady two-tick round trip (100 ms of sim time in
    lock-step, against 0 without) and predicts through two pending commands; the robots
    never brake for want of a command after the first two ticks, and all get home untouched."""
    sim, bridge, _ = run_pair(tmp_path, ["--ticks", "160", "--playout-ticks", "2"], SCRIPTED)
    assert bridge["round_trip_ms"]["p50"] == pytest.approx(100.0) == bridge["round_trip_ms"]["max"]
    applied = [t["applied"] for t in sim["trace"]]
    assert all(mode == "idle" for mode in applied[0] + applied[1])   # nothing due yet
    assert all(mode == "run" for modes in applied[2:] for mode in modes)
    assert_task_done(sim)
