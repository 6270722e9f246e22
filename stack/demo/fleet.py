"""Fleet stages: `fleet-sim` and `bridge` as separate processes over loopback Zenoh.

    fleet-sim  pymunk world with model error (:func:`model_error`), lock-step, --episodes K,
               listening on tcp/127.0.0.1:<free port>, multicast scouting off
    bridge     ControlStack(policy.onnx -> barrier-QP safety filter -> Kalman MEC), connecting
               to it, --episode-ticks T (the stack is reset at each episode)

Stage ``fleet`` runs the 5-robot policy (``policy.onnx``) on paper-5; stage ``fleet-unseen``
runs the generalist (``generalist/policy.onnx``, trained on 3-5 robots) on a team size it never
trained on (:data:`stack.demo.stages.UNSEEN_ROBOTS`, the default layout of that size).

The fleet-sim ends by itself after K episodes (one JSON line per finished episode feeds the
progress bar); the bridge is then stopped with SIGTERM (its clean path: loop stopped, Zenoh
session closed, report written). Both must exit with 0. Their reports (``fleet/sim.json``,
``fleet/bridge.json``) and logs stay in the demo folder; the stage result merges them per
episode: success, final distance [m], collision onsets, ticks with a safety intervention, MEC
tracking error [m] (:class:`stack.commands.bridge.EpisodeCounters`), the stack's tick time
and the Zenoh round trip [ms].
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from stack.demo.stages import GENERALIST_DIR, POLICY, UNSEEN_ROBOTS
from stack.demo.state import Children, DemoError, DemoSettings

SCENARIO = "paper-5"
UNSEEN_SCENARIO = f"transport-{UNSEEN_ROBOTS}"
UNSEEN_DIR = "fleet-unseen"
START_TIMEOUT_S = 180.0    # interpreter + torch + policy start-up on a loaded machine
EPISODE_STALL_S = 300.0    # no episode finished for this long: something is wrong
LOCKSTEP_TIMEOUT_S = 0.5   # per tick, above the bridge's 0.2 s gather; a missing answer is counted
STOP_TIMEOUT_S = 30.0


def model_error():
    """The 'real' robots: 70-90 % of the commanded acceleration, 50 ms actuator lag, floor
    friction 0.05 m/s^2, measurement noise 1 mm and 5 mm/s (std)."""
    from sim.pymunk_world import ModelError

    return ModelError(gain=0.8, gain_spread=0.1, lag_tau=0.05, floor_friction=0.05,
                      position_noise_std=0.001, velocity_noise_std=0.005)


def tracking_noise_floor(me: dict, dt: float, damping: float) -> float:
    """Expected tracking error [m] of a robot that follows the nominal model exactly.

    The prediction from the measured state is ``p^ = p_m(k) + dt v'``, ``v' = v_m + dt (a - c v_m)``
    (speed limit not reached), with ``p_m = p + n_p`` and ``v_m = v + n_v``. The error
    ``p_m(k+1) - p^`` then holds only noise: per axis ``n_p(k+1) - n_p(k) - dt (1 - c dt) n_v(k)``,
    std ``s = sqrt(2 s_p^2 + (dt (1 - c dt) s_v)^2)``; the mean norm of a 2-D isotropic Gaussian
    is ``s sqrt(pi / 2)``. (1 mm and 5 mm/s at dt = 0.05 s, c = 0.5/s: 1.80 mm.)
    """
    k = dt * (1.0 - damping * dt)
    s = math.sqrt(2 * me["position_noise_std"] ** 2 + (k * me["velocity_noise_std"]) ** 2)
    return s * math.sqrt(math.pi / 2)


def _tail(path: Path, lines: int = 20) -> str:
    try:
        return "".join(path.read_text(errors="replace").splitlines(keepends=True)[-lines:])
    except OSError:
        return ""


def _pump(stream, log_path: Path, lines: queue.Queue) -> None:
    """Copy a child's output into its log; hand JSON lines of finished episodes to ``lines``."""
    with log_path.open("w") as log:
        for line in stream:
            log.write(line)
            log.flush()
            if line.startswith("{") and '"episode"' in line:
                try:
                    lines.put(json.loads(line))
                except ValueError:
                    pass


def fleet_stage(settings: DemoSettings, out: Path, children: Children, *, scenario: str = SCENARIO,
                policy: str = POLICY, folder_name: str = "fleet") -> dict[str, Any]:
    """Run ``settings.fleet_episodes`` episodes of ``scenario`` over Zenoh with the exported
    ``policy`` (relative to ``out``), files into ``out / folder_name``; return the merged result."""
    from deploy.network import free_tcp_port
    from sim.scenario import make_scenario

    folder = out / folder_name
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("sim.json", "bridge.json"):   # from an interrupted attempt
        (folder / name).unlink(missing_ok=True)
    dynamics = make_scenario(scenario).dynamics
    ticks = dynamics.episode_steps
    episodes = settings.fleet_episodes
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    fleet = f"demo-{os.getpid()}"
    cli = [sys.executable, "-m", "stack.cli"]
    me = model_error()
    lines: queue.Queue = queue.Queue()
    sim = children.spawn(
        cli + ["fleet-sim", "--fleet", fleet, "--scenario", scenario, "--lockstep",
               "--episodes", str(episodes), "--seed", str(settings.seed), "--listen", endpoint,
               "--model-error", json.dumps(dataclasses.asdict(me)),
               "--lockstep-timeout", str(LOCKSTEP_TIMEOUT_S), "--start-timeout", str(START_TIMEOUT_S),
               "--report", str(folder / "sim.json")],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    pump = threading.Thread(target=_pump, args=(sim.stdout, folder / "sim.log", lines), daemon=True)
    pump.start()
    with (folder / "bridge.log").open("w") as bridge_log:
        bridge = children.spawn(
            cli + ["bridge", "--fleet", fleet, "--scenario", scenario, "--policy", str(out / policy),
                   "--connect", endpoint, "--episode-ticks", str(ticks), "--lockstep",
                   "--report", str(folder / "bridge.json")],
            stdout=bridge_log, stderr=subprocess.STDOUT)
    _watch(sim, bridge, lines, pump, folder, episodes, f"fleet over Zenoh ({scenario}, pymunk)", children)
    _stop(sim, bridge, folder, children)
    children.forget(sim)
    children.forget(bridge)
    sim_report = json.loads((folder / "sim.json").read_text())
    bridge_report = json.loads((folder / "bridge.json").read_text())
    result = merge_reports(sim_report, bridge_report, episodes, ticks, dataclasses.asdict(me),
                           scenario=scenario, policy=policy, folder_name=folder_name)
    result["tracking_noise_floor_m"] = tracking_noise_floor(result["model_error"], dynamics.dt,
                                                           dynamics.damping)
    return result


def _watch(sim: subprocess.Popen, bridge: subprocess.Popen, lines: queue.Queue, pump: threading.Thread,
           folder: Path, episodes: int, title: str, children: Children) -> list[dict]:
    """Follow fleet-sim's episode records until it exits (a progress bar of ``episodes``);
    DemoError, every child stopped, if the bridge exits first or no episode finishes in time."""
    finished: list[dict] = []
    with tqdm(total=episodes, unit="ep", desc=title, dynamic_ncols=True) as bar:
        def take(record: dict) -> None:
            finished.append(record)
            bar.update(1)
            bar.set_postfix(success=f"{np.mean([r['success'] for r in finished]):.2f}")

        last_progress = time.monotonic()
        while sim.poll() is None:
            try:
                take(lines.get(timeout=0.2))
                last_progress = time.monotonic()
            except queue.Empty:
                pass
            limit = START_TIMEOUT_S + EPISODE_STALL_S if not finished else EPISODE_STALL_S
            if bridge.poll() is not None and sim.poll() is None:
                children.terminate_all()
                raise DemoError(f"the bridge exited with code {bridge.returncode} before the fleet "
                                f"finished; its log ({folder / 'bridge.log'}):\n{_tail(folder / 'bridge.log')}")
            if time.monotonic() - last_progress > limit:
                children.terminate_all()
                raise DemoError(f"no fleet episode finished in {limit:.0f} s; logs in {folder}:\n"
                                f"{_tail(folder / 'sim.log')}\n{_tail(folder / 'bridge.log')}")
        pump.join(timeout=10)
        while not lines.empty():
            take(lines.get())
    return finished


def _stop(sim: subprocess.Popen, bridge: subprocess.Popen, folder: Path, children: Children) -> None:
    """After fleet-sim's exit: DemoError unless it succeeded and the bridge stops cleanly on SIGTERM."""
    if sim.returncode != 0:
        children.terminate_all()
        raise DemoError(f"fleet-sim exited with code {sim.returncode}; its log "
                        f"({folder / 'sim.log'}):\n{_tail(folder / 'sim.log')}")
    if bridge.poll() is None:
        os.killpg(bridge.pid, signal.SIGTERM)   # the bridge's clean shutdown path
    try:
        bridge.wait(timeout=STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        children.terminate_all()
        raise DemoError(f"the bridge did not stop within {STOP_TIMEOUT_S:.0f} s of SIGTERM") from None
    if bridge.returncode != 0:
        raise DemoError(f"the bridge exited with code {bridge.returncode}; its log "
                        f"({folder / 'bridge.log'}):\n{_tail(folder / 'bridge.log')}")


def unseen_fleet_stage(settings: DemoSettings, out: Path, children: Children) -> dict[str, Any]:
    """The generalist's exported policy on :data:`UNSEEN_SCENARIO`, a team size it never trained on."""
    return fleet_stage(settings, out, children, scenario=UNSEEN_SCENARIO, policy=f"{GENERALIST_DIR}/{POLICY}",
                       folder_name=UNSEEN_DIR)


def _pct(records: list[dict], key: str, which: str) -> float | None:
    values = [r[key][which] for r in records if r.get(key)]
    if not values:
        return None
    return float(np.median(values)) if which == "p50" else float(np.max(values))


def merge_reports(sim: dict, bridge: dict, episodes: int, ticks: int, model_error: dict, *,
                  scenario: str = SCENARIO, policy: str = POLICY, folder_name: str = "fleet") -> dict[str, Any]:
    """Per-episode rows from the fleet-sim (judged on the true state) and the bridge (the
    stack's counters), and their totals. Latency: median of the episodes' p50, worst p99."""
    by_index = {r["episode"]: r for r in bridge.get("episodes", [])}
    rows = []
    for s in sim["episodes"]:
        b = by_index.get(s["episode"], {})
        rows.append({
            "episode": s["episode"], "seed": s["seed"], "ticks": s["ticks"],
            "bridge_ticks": b.get("ticks"), "success": s["success"],
            "final_distance": s["final_distance"], "collisions": sum(s["collisions"].values()),
            "collisions_by_kind": s["collisions"], "interventions": b.get("interventions"),
            "infeasible": b.get("infeasible"), "fallbacks": b.get("fallbacks"),
            "braking": b.get("braking"), "tracking_error_m": b.get("tracking_error"),
            "tick_ms": b.get("tick_ms"), "round_trip_ms": s.get("round_trip_ms"),
            "lockstep_timeouts": s["lockstep_timeouts"]})
    if len(rows) != episodes:
        raise DemoError(f"the fleet-sim reported {len(rows)} episodes, {episodes} were asked for")
    tracking = [r["tracking_error_m"] for r in rows if r["tracking_error_m"] is not None]
    return {
        "episodes": len(rows), "scenario": scenario, "world": "pymunk", "model_error": model_error,
        "policy": policy, "safety": True, "mec": True, "episode_ticks": ticks,
        "success_rate": float(np.mean([r["success"] for r in rows])),
        "final_distance": float(np.mean([r["final_distance"] for r in rows])),
        "collisions": int(sum(r["collisions"] for r in rows)),
        "collision_episodes": int(sum(r["collisions"] > 0 for r in rows)),
        "interventions": int(sum(r["interventions"] or 0 for r in rows)),
        "tracking_error_m": float(np.mean(tracking)) if tracking else None,
        "tick_ms": {"p50": _pct(rows, "tick_ms", "p50"), "p99": _pct(rows, "tick_ms", "p99")},
        "round_trip_ms": {"p50": _pct(rows, "round_trip_ms", "p50"),
                          "p99": _pct(rows, "round_trip_ms", "p99")},
        "lockstep_timeouts": int(sim["lockstep_timeouts"]),
        "bridge": {k: bridge.get(k) for k in ("ticks", "robot_counts", "estops", "controller_faults",
                                               "stale_marks", "rejects")},
        "sim_rejects": sim.get("rejects"),
        "per_episode": rows,
        "reports": {"sim": f"{folder_name}/sim.json", "bridge": f"{folder_name}/bridge.json",
                    "logs": [f"{folder_name}/sim.log", f"{folder_name}/bridge.log"]},
    }


__all__ = ["SCENARIO", "UNSEEN_DIR", "UNSEEN_SCENARIO", "fleet_stage", "merge_reports", "model_error",
           "tracking_noise_floor", "unseen_fleet_stage"]
