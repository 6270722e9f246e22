"""bench/fleet_loop.py: a tiny run over real Zenoh (output shape; no timing limits), and the raw
peer's pong counting by hand."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest

from bench.fleet_loop import PongCounter, payload_tick, ping_payload
from tests.bench import ROOT, run_json

realtime = pytest.mark.realtime   # Zenoh round trips at 50 Hz

KEYS = {"ticks", "p50_ms", "p99_ms", "max_ms", "missed", "unanswered"}


@realtime
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


@realtime
def test_bad_robot_list_is_an_error():
    result = subprocess.run([sys.executable, str(ROOT / "bench" / "fleet_loop.py"), "--robots",
                             "0"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "positive integer" in result.stderr


def test_a_ping_carries_its_tick_in_64_bytes():
    assert len(ping_payload(7)) == 64 and payload_tick(ping_payload(7)) == 7
    assert payload_tick(ping_payload(2**40 + 3)) == 2**40 + 3


def test_a_late_pong_answers_no_later_tick():
    """Two robots. Tick 1: robot 0 answers, robot 1's pong is late (the tick times out). Tick 2:
    robot 1's late pong of tick 1 arrives first; tick 2 is answered only once both robots sent
    pongs carrying 2."""
    counter = PongCounter(2)
    assert counter.start() == 1
    counter.record(0, 1)
    assert not counter.complete()
    assert counter.start() == 2          # tick 1 timed out
    counter.record(1, 1)                 # the late pong of tick 1
    counter.record(0, 2)
    assert not counter.complete()
    counter.record(1, 2)
    assert counter.complete()
