"""Compiled kernels: the control tick never compiles, bad shapes are refused before a kernel runs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from controllers.safety.latency import LatencyPredictor
from sim.scenario import Dynamics

ROOT = Path(__file__).resolve().parents[2]

EPISODES = """
import json
from controllers.jit import KERNELS
from controllers.scripted import ScriptedController
from sim.pymunk_world import ModelError, PymunkWorld
from sim.scenario import make_scenario
from stack.pipeline import ControlStack, StackConfig, run_episode

after_warm_up = None
for name, error in [("exact", ModelError()),
                    ("link", ModelError(delay_ticks=2, delay_jitter_ticks=1, position_noise_std=0.01,
                                        velocity_noise_std=0.02, state_drop=0.2, gain=0.7)),
                    ("frozen", ModelError(freeze=(1, 20)))]:
    for robots in (3, 5):
        scenario = make_scenario(f"paper-{robots}")
        stack = ControlStack(scenario, ScriptedController(scenario), StackConfig())
        if after_warm_up is None:
            after_warm_up = {k.__name__: len(k.signatures) for k in KERNELS}
        run_episode(PymunkWorld(scenario, error), stack, seed=1, steps=60)
print(json.dumps({"after_warm_up": after_warm_up, "at_end": {k.__name__: len(k.signatures) for k in KERNELS}}))
"""


def test_the_warm_up_compiles_every_kernel_the_tick_runs_and_the_tick_compiles_nothing():
    """In a fresh process (kernels keep their signatures for the life of a process): after the
    first ControlStack, every kernel has its one signature, and episodes of 3 and 5 robots under
    delay, jitter, noise, dropped states and a frozen robot add none (a new signature is a
    compilation of seconds inside a tick)."""
    out = subprocess.run([sys.executable, "-c", EPISODES], cwd=ROOT, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    counts = json.loads(out.stdout.strip().splitlines()[-1])
    called_by_the_tick = ("observe", "compensate", "estimate", "predict_listening")
    assert [counts["after_warm_up"][name] for name in called_by_the_tick] == [1, 1, 1, 1], counts
    assert max(counts["after_warm_up"].values()) == 1   # the rest run inside those (no signature)
    assert counts["at_end"] == counts["after_warm_up"]


def test_a_row_count_that_does_not_match_is_refused_before_the_kernel_reads_it():
    """Kernels read their arrays unchecked: the predictor names the field instead."""
    pred = LatencyPredictor(Dynamics())
    pos, vel, ages, a_nom = np.zeros((3, 2)), np.zeros((3, 2)), np.zeros(3), np.zeros((3, 2))
    with pytest.raises(ValueError, match=r"pending must have shape \(3,\), got \(2,\)"):
        pred.predict(("a", "b", "c"), pos, vel, ages, a_nom, pending=np.zeros(2, dtype=int))
    with pytest.raises(ValueError, match=r"a_nom must have shape \(3, 2\), got \(1, 2\)"):
        pred.predict(("a", "b", "c"), pos, vel, ages, np.zeros((1, 2)))
