"""Smoke test of bench/jittery_link.py: one short bare episode over the relay, the JSON shape,
and bad arguments refused by name. No timing limits."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.realtime   # fleet-sim and the bridge on the wall clock

ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "bench" / "jittery_link.py"


def test_one_bare_episode_gives_a_row_with_the_relay_s_round_trips():
    result = subprocess.run([sys.executable, str(BENCH), "--seeds", "1", "--episode-ticks", "40", "--configs", "bare",
                             "--delay-ms", "30", "--jitter-ms", "5", "--json"], cwd=ROOT,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    document = json.loads(result.stdout.strip())
    assert {k: document[k] for k in ("delay_ms", "jitter_ms", "ticks", "brake_after_ticks")} == \
        {"delay_ms": 30.0, "jitter_ms": 5.0, "ticks": 40, "brake_after_ticks": 2}
    assert document["playout_ticks"] == 0
    (row,) = document["rows"]
    assert (row["config"], row["seed"]) == ("bare", 0)
    assert row["home_tick"] is None                 # 40 ticks are too few to get home (84 on a clean link)
    assert row["round_trip_ms"]["p50"] > 2 * 25.0   # there and back through the relay, at least
    assert set(row["collisions"]) == {"robot", "object", "wall"}


@pytest.mark.parametrize("args, message", [(["--jitter-ms", "30"], "--jitter-ms must lie in"),
                                           (["--configs", "stack,fast"], "--configs takes")])
def test_bad_arguments_are_refused_with_the_field_named(args, message):
    result = subprocess.run([sys.executable, str(BENCH), *args], cwd=ROOT, capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2 and message in result.stderr


def _document(argv, monkeypatch, capsys) -> tuple[dict, list[int], str]:
    """The JSON document of ``argv`` with each episode replaced by a stand-in that records the
    ticks it was asked for; and stderr."""
    sys.path.insert(0, str(ROOT))
    import bench.jittery_link as jittery_link

    asked = []

    def run(config, seed, args):
        asked.append(args.episode_ticks)
        return {"config": config, "seed": seed, "home_tick": None, "collisions": {}, "round_trip_ms": {},
                "watchdog_share": 0.0}

    monkeypatch.setattr(jittery_link, "run", run)
    assert jittery_link.main([*argv, "--seeds", "1", "--configs", "bare", "--json"]) == 0
    out = capsys.readouterr()
    return json.loads(out.out), asked, out.err


def test_episode_ticks_sets_the_ticks_of_each_episode_and_the_json_keeps_its_ticks_key(monkeypatch, capsys):
    document, asked, err = _document(["--episode-ticks", "7"], monkeypatch, capsys)
    assert asked == [7] and document["ticks"] == 7 and "warning" not in err
    document, asked, _ = _document([], monkeypatch, capsys)
    assert asked == [400] and document["ticks"] == 400


def test_ticks_still_sets_the_episode_ticks_and_warns(monkeypatch, capsys):
    document, asked, err = _document(["--ticks", "7"], monkeypatch, capsys)
    assert asked == [7] and document["ticks"] == 7
    assert "warning: --ticks is deprecated; use --episode-ticks\n" in err
