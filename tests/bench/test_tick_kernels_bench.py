"""Smoke test of bench/tick_kernels.py: a short run in a fresh process gives identical commands
from the compiled tick and its numpy formulation, and the JSON shape the docstring names. No
timing limits."""

from __future__ import annotations

from tests.bench import run_json


def test_the_compiled_tick_and_its_numpy_formulation_send_identical_commands():
    document = run_json("tick_kernels.py", "--robots", "4", "--ticks", "150", "--warmup", "10")
    assert (document["robots"], document["ticks"], document["identical_commands"]) == (4, 150, True)
    stages = {"total", "observe", "policy", "safety", "mec"}
    for name in ("compiled", "numpy"):
        assert set(document[name]) == stages
        assert all(document[name][s]["p99"] >= document[name][s]["p50"] > 0 for s in stages)
    assert set(document["speedup_p50"]) == stages
