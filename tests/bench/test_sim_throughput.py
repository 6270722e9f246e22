"""Smoke tests of bench/sim_throughput.py: tiny runs, output shape, errors. No timing limits."""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "bench" / "sim_throughput.py"
ROW_KEYS = {"sim", "robots", "envs", "steps_per_s"}


def _load_script():
    spec = importlib.util.spec_from_file_location("sim_throughput_bench", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


bench = _load_script()
TINY = ["--envs", "1,2", "--robots", "3", "--steps", "3", "--repeats", "2", "--warmup", "1"]


def _check_rows(rows, sims, envs=(1, 2), robots=(3,)):
    assert [(r["robots"], r["envs"], r["sim"]) for r in rows] == [
        (n, e, s) for n in robots for e in envs for s in sims]
    for r in rows:
        assert set(r) == ROW_KEYS
        assert isinstance(r["robots"], int) and isinstance(r["envs"], int)
        assert isinstance(r["steps_per_s"], float)
        assert math.isfinite(r["steps_per_s"]) and r["steps_per_s"] > 0


def test_json_without_peer_has_exact_row_keys_and_clean_stdout(capsys):
    assert bench.main(TINY + ["--no-peer", "--json"]) == 0
    out, err = capsys.readouterr()
    doc = json.loads(out)           # stdout is one JSON document and nothing else
    _check_rows(doc["rows"], ["formation", "formation-training-reward"])
    assert doc["torch_threads"] == 1
    assert doc["vmas"] is None
    assert "formation" in err       # progress went to stderr


def test_json_with_vmas_measures_both_scenarios(capsys):
    pytest.importorskip("vmas")
    assert bench.main(TINY + ["--json", "--threads", "1"]) == 0
    doc = json.loads(capsys.readouterr().out)
    _check_rows(doc["rows"], ["formation", "formation-training-reward", "vmas-transport", "vmas-navigation"])
    assert doc["vmas"] == "1.5.2"


def test_table_ratio_is_rate_over_vmas_transport_of_same_pair():
    rows = [
        {"sim": "formation", "robots": 3, "envs": 64, "steps_per_s": 300.0},
        {"sim": "vmas-transport", "robots": 3, "envs": 64, "steps_per_s": 100.0},
        {"sim": "vmas-navigation", "robots": 3, "envs": 64, "steps_per_s": 50.0},
        {"sim": "formation", "robots": 5, "envs": 64, "steps_per_s": 80.0},
    ]
    assert bench.ratio_vs_reference(rows) == [3.0, 1.0, 0.5, None]
    table = bench.table_rows(rows)
    assert [r[-1] for r in table] == ["3.00x", "1.00x", "0.50x", "-"]


def test_median_rates_warm_up_then_interleave_repeats():
    log: list[tuple[str, int]] = []
    steppers = {name: (lambda k, name=name: log.append((name, k))) for name in ("a", "b")}
    rates = bench.median_rates(steppers, steps=2, repeats=2, warmup=1, items_per_call=10)
    assert log == [("a", 0), ("b", 0),                 # warm-up
                   ("a", 1), ("a", 2), ("b", 1), ("b", 2),   # repeat 1
                   ("a", 3), ("a", 4), ("b", 3), ("b", 4)]   # repeat 2
    assert set(rates) == {"a", "b"} and all(r > 0 for r in rates.values())


def test_median_rates_rejects_zero_steps():
    with pytest.raises(ValueError, match="steps"):
        bench.median_rates({"a": lambda k: None}, steps=0, repeats=1, warmup=0, items_per_call=1)


def test_formation_stepper_cycles_actions_and_returns_tokens():
    step = bench.formation_stepper(robots=3, envs=2, seed=0)
    result = step(0)
    assert tuple(result.obs.shape) == (2, 3, 7, 4)
    assert tuple(result.reward.shape) == (2, 3)


@pytest.mark.parametrize("argv, field", [
    (["--envs", "0"], "--envs"),
    (["--robots", "3,x"], "--robots"),
    (["--robots", "22"], "--robots"),
    (["--steps", "0"], "--steps"),
    (["--warmup", "-1"], "--warmup"),
])
def test_bad_arguments_name_the_flag(argv, field, capsys):
    with pytest.raises(SystemExit) as info:
        bench.main(argv + ["--no-peer"])
    assert info.value.code == 2
    assert field in capsys.readouterr().err


def test_missing_vmas_exits_nonzero_and_names_the_fix():
    # Python's import system refuses a module whose sys.modules entry is None.
    code = ("import runpy, sys; sys.modules['vmas'] = None; sys.argv = [sys.argv[0]] + sys.argv[1:]; "
            f"runpy.run_path({str(SCRIPT)!r}, run_name='__main__')")
    proc = subprocess.run([sys.executable, "-c", code, *TINY], capture_output=True, text=True,
                          timeout=120, cwd=ROOT)
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert "vmas" in proc.stderr and "--no-peer" in proc.stderr and "[bench]" in proc.stderr


@pytest.mark.parametrize("argv, peer", [([], True), (["--peer"], True), (["--no-peer"], False),
                                        (["--no-peer", "--peer"], True)])
def test_the_peer_is_an_on_off_flag_on_by_default(argv, peer):
    """--peer/--no-peer, the spelling of every on/off setting: the last one given wins."""
    assert bench.build_parser().parse_args(argv).peer is peer
