"""Smoke test of bench/fleet_loop.py: a tiny run over real Zenoh, output shape. No timing limits."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest

from tests.bench import ROOT, run_json

pytestmark = pytest.mark.realtime   # Zenoh round trips at 50 Hz

KEYS = {"ticks", "p50_ms", "p99_ms", "max_ms", "missed", "unanswered"}


def test_json_has_one_entry_per_robot_count_and_the_peer():
    document = run_json("fleet_loop.py", "--robots", "2,3", "--ticks", "15")
    assert set(document) == {"2", "3", "peer_raw_zenoh", "tls_router"}
    tls = document["tls_router"]
    assert set(tls) == {"2", "3"}
    for n in ("2", "3"):    # the p50 ratio to the plain row of the same run
        assert tls[n].pop("p50_vs_plain") == round(tls[n]["p50_ms"] / document[n]["p50_ms"], 3)
    for entry in (document["2"], document["3"], *document["peer_raw_zenoh"].values(), *tls.values()):
        assert set(entry) == KEYS and entry["ticks"] == 15
        assert 0 <= entry["unanswered"] <= entry["missed"] <= 15
        assert all(math.isfinite(entry[k]) and entry[k] > 0 for k in ("p50_ms", "p99_ms", "max_ms"))
        assert entry["p50_ms"] <= entry["p99_ms"] <= entry["max_ms"]


def test_bad_robot_list_is_an_error():
    result = subprocess.run([sys.executable, str(ROOT / "bench" / "fleet_loop.py"), "--robots",
                             "0"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "positive integer" in result.stderr
