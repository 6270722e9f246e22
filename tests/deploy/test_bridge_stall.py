"""The bridge's recovery rule after a stall, with real processes: fleet-sim in real time (20 Hz)
and the bridge (scripted policy, safety filter and MEC on) over Zenoh on 127.0.0.1.

The bridge process is frozen with SIGSTOP for 3 s mid-run and resumed with SIGCONT. The robots'
watchdogs brake and latch them meanwhile. The rule (deploy/bridge_picture.py, docs/wire-format.md):
the bridge discards its old picture, raises no e-stop for its own stall, and re-arms every
latched robot through FAULT -> STOP once fresh states arrive; the fleet drives on. Before the
rule, the same experiment ended e-stopped in about half the runs and drove on in the others.
"""

from __future__ import annotations

import json
import signal
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from deploy.network import free_tcp_port

sys.path.insert(0, str(Path(__file__).parent))
from test_fleet_sim_bridge import Proc, finish_pair, killed_on_exit  # noqa: E402

pytestmark = pytest.mark.realtime   # fleet-sim and bridge processes, a 3 s SIGSTOP

RUNS = 5
SIDE_BY_SIDE = 2   # runs at a time
FREEZE_S = 3.0
TICKS = 180   # 9 s at 20 Hz from the bridge's first tick: the freeze ends near tick 80


def frozen_run(tmp_path: Path) -> dict:
    """One run in ``tmp_path`` (its fleet named after the folder, so runs side by side never mix)."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    fleet = f"stall-{tmp_path.name}"
    sim = Proc("fleet-sim", "--fleet", fleet, "--scenario", "paper-5", "--rate-hz", "20",
               "--listen", endpoint, "--ticks", str(TICKS), "--report", str(tmp_path / "sim.json"))
    with killed_on_exit([sim]) as procs:
        procs.append(bridge := Proc("bridge", "--fleet", fleet, "--scenario", "paper-5", "--policy", "scripted",
                                    "--connect", endpoint, "--print-ticks", "--report", str(tmp_path / "bridge.json")))
        bridge.wait_tick(20)
        bridge.proc.send_signal(signal.SIGSTOP)
        time.sleep(FREEZE_S)
        bridge.proc.send_signal(signal.SIGCONT)
        finish_pair(sim, bridge)
    return {"sim": json.loads((tmp_path / "sim.json").read_text()),
            "bridge": json.loads((tmp_path / "bridge.json").read_text())}


def outcome(run: dict) -> dict:
    """What a run came to: e-stopped or not, every robot latched then driving again, each
    re-arm answered before the re-arm alarm (deploy/rearm_watch.py) would call it refusing."""
    modes = [t["modes"] for t in run["sim"]["trace"]]
    latched = [i for i, m in enumerate(modes) if m == ["latched"] * 5]
    again = latched and any(m == ["run"] * 5 for m in modes[latched[-1]:])
    return {"estop": run["bridge"]["estop_engaged"] or run["bridge"]["estops"] > 0,
            "stalls": run["bridge"]["stalls"], "all_latched": bool(latched),
            "all_rearmed": run["bridge"]["rearms"] >= 5, "driving_again": bool(again),
            "rearm_alarm": run["bridge"]["rearm_alarms"] > 0 or bool(run["bridge"]["refusing"])}


@pytest.mark.slow
def test_a_frozen_bridge_recovers_by_one_rule_in_every_run(tmp_path):
    folders = [tmp_path / f"run{k}" for k in range(RUNS)]
    for folder in folders:
        folder.mkdir()
    with ThreadPoolExecutor(SIDE_BY_SIDE) as pool:   # each run mostly waits on the wall clock
        runs = list(pool.map(frozen_run, folders))
    outcomes = [outcome(r) for r in runs]
    expected = {"estop": False, "stalls": 1, "all_latched": True, "all_rearmed": True,
                "driving_again": True, "rearm_alarm": False}
    assert outcomes == [expected] * RUNS
    for run in runs:
        assert run["bridge"]["longest_stall_s"] > FREEZE_S - 0.5
        assert run["sim"]["collisions"] == {"robot": 0, "object": 0, "wall": 0}
        assert np.isfinite(run["sim"]["final_distance"])
    print("\nre-arms in a row:", [r["bridge"]["rearms_in_a_row"] for r in runs])
    print("final distances after the freeze:",
          [round(r["sim"]["final_distance"], 3) for r in runs],
          "success:", [r["sim"]["success"] for r in runs])
