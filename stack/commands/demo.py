"""`formation demo`: the main job, end to end, on embedded defaults.

Until the learned pipeline is wired in (training, transfer, export, fleet over Zenoh), this
runs the best end-to-end path that exists and says so: the scripted controller on the
paper's 3, 4 and 5 robot presets in the batched world, judged by the shared metrics.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from controllers.scripted import ScriptedController
from sim.fleet import BatchedFleet
from sim.metrics import collision_events, episode_outcome
from sim.scenario import make_scenario


def register(sub) -> None:
    p = sub.add_parser("demo", help="run the main job end to end and write a report",
                       description=__doc__)
    p.add_argument("--out", type=Path, default=None, help="output folder (default runs/demo-<timestamp>)")
    p.add_argument("--episodes", type=int, default=10, help="episodes per preset (default 10)")
    p.set_defaults(func=run)


def run(args) -> int:
    out = args.out or Path("runs") / time.strftime("demo-%Y%m%d-%H%M%S")
    out.mkdir(parents=True, exist_ok=True)
    print("formation demo: the learned pipeline is not wired in yet; running the scripted "
          "controller end to end in the batched world.")
    results = {}
    for name in ("paper-3", "paper-4", "paper-5"):
        sc = make_scenario(name)
        fleet, ctl = BatchedFleet(sc), ScriptedController(sc)
        succ, dist, coll = [], [], 0
        for ep in tqdm(range(args.episodes), desc=name, unit="ep"):
            state, collided = fleet.reset(seed=ep), False
            ctl.reset()
            for _ in range(sc.dynamics.episode_steps):
                fleet.send_accelerations(ctl(state))
                state = fleet.step()
                ev = collision_events(torch.tensor(state.positions)[None], torch.tensor(sc.polygon),
                                      sc.robot_radius, sc.arena)
                collided |= bool(ev.any.any())
            o = episode_outcome(torch.tensor(state.positions)[None], torch.tensor(state.targets)[None],
                                torch.tensor([collided]), sc.target_tolerance)
            succ.append(bool(o.success)), dist.append(float(o.final_distance))
            coll += int(collided)
        results[name] = {"episodes": args.episodes, "success_rate": float(np.mean(succ)),
                         "final_distance": float(np.mean(dist)), "collision_episodes": coll}
    print(f"{'preset':<8} {'success':>8} {'final dist [m]':>15} {'collisions':>10}")
    for name, r in results.items():
        print(f"{name:<8} {r['success_rate']:>8.2f} {r['final_distance']:>15.4f} {r['collision_episodes']:>10d}")
    tmp = out / "metrics.json.tmp"
    tmp.write_text(json.dumps({"controller": "scripted", "results": results}, indent=2))
    os.replace(tmp, out / "metrics.json")
    print(f"wrote {out / 'metrics.json'}")
    return 0
