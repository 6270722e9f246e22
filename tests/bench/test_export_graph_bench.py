"""Smoke test of bench/export_graph.py: a short run in a fresh process gives the JSON shape the
docstring names, the rewritten graph smaller than the actor's own and both within the export
tolerance of the eager actor. No timing limits."""

from __future__ import annotations

from deploy.export import TOLERANCE
from tests.bench import run_json


def test_the_rewritten_graph_is_smaller_and_both_match_the_actor():
    document = run_json("export_graph.py", "--robots", "3", "--ticks", "100", "--warmup", "10")
    assert (document["robots"], document["ticks"]) == (3, 100)
    graphs = document["graphs"]
    assert set(graphs) == {"actor", "rows"}
    assert graphs["rows"]["nodes"] <= 58 < 100 < graphs["actor"]["nodes"]
    for g in graphs.values():
        assert g["max_abs_diff"] <= TOLERANCE
        for key in ("call_ms", "tick_ms", "policy_stage_ms"):
            assert g[key]["p99"] >= g[key]["p50"] > 0
    assert set(document["speedup_p50"]) == {"call", "policy_stage", "tick"}
