"""bench/_common.py: what every benchmark's JSON document records of the code that made it, and the
argparse types the benchmarks share."""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys

import pytest

from tests.bench import ROOT

sys.path.insert(0, str(ROOT / "bench"))
import _common  # noqa: E402


def test_a_document_records_the_checkout_it_started_from(monkeypatch, capsys):
    """A long run outlives commits made beside it: the document names the checkout at the start
    (the code that ran) and, when the checkout changed meanwhile, the one at the end beside it."""
    monkeypatch.setattr(_common, "GIT_AT_START", {"commit": "0" * 40, "dirty": False})
    _common.print_json({"x": 1})
    made = json.loads(capsys.readouterr().out)["provenance"]
    assert made["git"] == {"commit": "0" * 40, "dirty": False}
    assert len(made["git_at_end"]["commit"]) == 40 and made["git_at_end"]["commit"] != "0" * 40
    monkeypatch.setattr(_common, "GIT_AT_START", made["git_at_end"])
    _common.print_json({"x": 1})
    again = json.loads(capsys.readouterr().out)["provenance"]
    assert again["git"] == made["git_at_end"] and "git_at_end" not in again


def test_robot_counts_are_bounded_by_max_robots():
    assert _common.MAX_ROBOTS == 21
    assert _common.robot_count("21") == 21 and _common.robot_count_list("1, 21") == [1, 21]
    for bad in ("22", "0", "-3", "x"):
        with pytest.raises(argparse.ArgumentTypeError, match="1..21"):
            _common.robot_count(bad)
        with pytest.raises(argparse.ArgumentTypeError, match="1..21"):
            _common.robot_count_list(f"3,{bad}")


def test_nonnegative_int_and_positive_float_by_hand():
    assert _common.nonnegative_int("0") == 0 and _common.nonnegative_int("7") == 7
    with pytest.raises(argparse.ArgumentTypeError, match=">= 0"):
        _common.nonnegative_int("-1")
    assert _common.positive_float("0.25") == 0.25 and _common.positive_float("3") == 3.0
    for bad in ("nan", "inf", "-inf", "0", "-1", "x"):
        with pytest.raises(argparse.ArgumentTypeError, match="finite number > 0"):
            _common.positive_float(bad)


def _script(name: str):
    spec = importlib.util.spec_from_file_location(f"bench_script_{name}", ROOT / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module         # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("script, argv", [
    ("tick_kernels", ["--robots", "22", "--ticks", "1", "--warmup", "1"]),
    ("export_graph", ["--robots", "30", "--ticks", "1", "--warmup", "1"]),
    ("safety", ["--only", "latency", "--robots", "3,30", "--ticks", "1", "--warmup", "1"]),
    ("generalization", ["--robots", "3,22", "--policies", str(ROOT / "no-such-checkpoint.pt")]),
    ("sim_throughput", ["--robots", "22", "--no-peer"]),
])
def test_robots_above_max_robots_exit_2_naming_the_flag(script, argv, capsys):
    """Every --robots the scenarios place: more than MAX_ROBOTS is a usage error, not a traceback."""
    with pytest.raises(SystemExit) as info:
        _script(script).main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2 and "argument --robots" in err and "1..21" in err


@pytest.mark.parametrize("script, argv", [
    ("tick_kernels", ["--ticks", "1", "--warmup", "1"]),
    ("export_graph", ["--ticks", "1", "--warmup", "1"]),
    ("safety", ["--only", "mec", "--mec-episodes", "1"]),
    ("train_speed", ["--settings", "paper-3", "--repeats", "1", "--episodes", "16"]),
    ("sim_throughput", ["--envs", "1", "--robots", "3", "--steps", "1", "--repeats", "1", "--no-peer"]),
])
@pytest.mark.parametrize("seed", ["-1", "4294967296", "x"])
def test_a_bad_seed_exits_2_naming_the_flag_before_any_work(script, argv, seed, capsys):
    """Every bench --seed is a `formation` seed (0 .. 2**32 - 1), refused at parse time; it was a
    traceback from the simulator or the trainer minutes in."""
    with pytest.raises(SystemExit) as info:
        _script(script).main([*argv, "--seed", seed])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "argument --seed" in err and "Traceback" not in err


BENCHES = ["export_graph", "fleet_loop", "generalization", "jittery_link", "link_congestion",
           "paper_tables", "safety", "sim_throughput", "tick_kernels", "train_speed"]


class _Parsed(Exception):
    """Raised in place of parsing: carries the parser a benchmark built."""


def _parser_of(script: str, monkeypatch) -> argparse.ArgumentParser:
    def capture(self, args=None, namespace=None):
        raise _Parsed(self)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", capture)
    module = _script(script)
    with pytest.raises(_Parsed) as parsed:
        module.main([])
    return parsed.value.args[0]


@pytest.mark.parametrize("script", BENCHES)
def test_every_bench_flag_has_help_that_states_its_default(script, monkeypatch):
    """Every visible option says what it does, and one with a default (other than off or none)
    says which."""
    parser = _parser_of(script, monkeypatch)
    for action in parser._actions:
        if action.help == argparse.SUPPRESS or isinstance(action, argparse._HelpAction):
            continue
        flag = "/".join(action.option_strings)
        assert action.help, f"{script} {flag}: no help"
        if action.default not in (None, False, argparse.SUPPRESS):
            assert "default" in action.help, f"{script} {flag}: no default in {action.help!r}"


@pytest.mark.parametrize("script, old, new", [
    ("safety", "--steps", "--episode-ticks"),
    ("safety", "--workers", "--cpus"),
    ("paper_tables", "--jobs", "--cpus"),
    ("generalization", "--episodes", "--eval-episodes"),
    ("jittery_link", "--ticks", "--episode-ticks"),
    ("link_congestion", "--robots", "--burst"),
])
def test_a_renamed_bench_flag_is_hidden_and_its_new_name_is_in_the_help(script, old, new, monkeypatch):
    """One name per concept: --cpus, --episode-ticks, --eval-episodes, --burst; the old
    spelling stays as a deprecated alias, out of --help (each script's tests show it still
    works and warns)."""
    text = _parser_of(script, monkeypatch).format_help()
    assert f"{new} " in text and f"{old} " not in text
