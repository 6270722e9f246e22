"""Smoke test of bench/export_graph.py: a short run in a fresh process gives the JSON shape the
docstring names, the rewritten graph smaller than the actor's own and both within the export
tolerance of the eager actor. No timing limits."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from deploy.export import TOLERANCE

ROOT = Path(__file__).resolve().parents[2]


def test_the_rewritten_graph_is_smaller_and_both_match_the_actor():
    result = subprocess.run([sys.executable, str(ROOT / "bench" / "export_graph.py"), "--robots", "3",
                             "--ticks", "100", "--warmup", "10", "--json"], cwd=ROOT, capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    document = json.loads(result.stdout.strip())
    assert (document["robots"], document["ticks"]) == (3, 100)
    graphs = document["graphs"]
    assert set(graphs) == {"actor", "rows"}
    assert graphs["rows"]["nodes"] <= 54 < 100 < graphs["actor"]["nodes"]
    for g in graphs.values():
        assert g["max_abs_diff"] <= TOLERANCE
        for key in ("call_ms", "tick_ms", "policy_stage_ms"):
            assert g[key]["p99"] >= g[key]["p50"] > 0
    assert set(document["speedup_p50"]) == {"call", "policy_stage", "tick"}
