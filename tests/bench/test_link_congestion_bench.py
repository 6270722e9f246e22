"""Smoke test of bench/link_congestion.py: a tiny run through two real network namespaces, the
output shape, and that a link fast enough for the traffic delivers every message of the fleet's
publishers. No timing limits."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.realtime   # a link paced on the wall clock

ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "bench" / "link_congestion.py"


@pytest.mark.skipif(os.geteuid() != 0 or not (shutil.which("ip") and shutil.which("tc")),
                    reason="needs root and iproute2 (ip netns, tc)")
def test_a_fast_link_delivers_every_message_and_the_json_has_a_row_per_run():
    result = subprocess.run([sys.executable, str(BENCH), "--rate-kbit", "100000", "--burst", "5",
                             "--ticks", "20", "--repeats", "1", "--json"], cwd=ROOT,
                            capture_output=True, text=True, timeout=180)
    assert result.returncode == 0, result.stderr
    document = json.loads(result.stdout.strip())
    assert {k: document[k] for k in ("rate_kbit", "robots", "period_ms", "ticks")} == \
        {"rate_kbit": 100000, "robots": 5, "period_ms": 20.0, "ticks": 20}
    fleet, express = document["rows"]
    assert (fleet["publishers"], express["publishers"]) == ("fleet", "express")
    assert fleet["sent"] == fleet["received"] == 100
    assert express["sent"] == 100 and 0 < express["received"] <= 100   # express may lose some
    for row in document["rows"]:
        assert 0 < row["age_ms"]["p50"] <= row["age_ms"]["p99"] <= row["age_ms"]["max"]


def test_bad_arguments_are_refused_with_the_field_named():
    result = subprocess.run([sys.executable, str(BENCH), "--period-ms", "0"], cwd=ROOT,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "--period-ms must be > 0" in result.stderr


def _sent(argv, monkeypatch) -> list[int]:
    """The messages a burst of the sender role, its publishing replaced by a stand-in."""
    sys.path.insert(0, str(ROOT))
    import bench.link_congestion as link_congestion

    bursts = []
    monkeypatch.setattr(link_congestion, "send", lambda publishers, robots, ticks, period_s: bursts.append(robots) or 0)
    assert link_congestion.main([*argv, "--role", "send", "--publishers", "fleet"]) == 0
    return bursts


def test_burst_sets_the_messages_of_a_burst(monkeypatch, capsys):
    assert _sent(["--burst", "7"], monkeypatch) == [7] and _sent([], monkeypatch) == [50]
    assert capsys.readouterr().err == ""


def test_robots_still_sets_the_burst_and_warns(monkeypatch, capsys):
    assert _sent(["--robots", "7"], monkeypatch) == [7]
    assert capsys.readouterr().err == "warning: --robots is deprecated; use --burst\n"
