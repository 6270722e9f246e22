"""One flag style across commands: the same spelling for the same switch, errors on stderr."""

from __future__ import annotations

import pytest

import stack.commands.scenarios as scenarios_command
from stack.cli import main
from tests.signals import define_a_class_under_sigint


@pytest.mark.parametrize("command", ["eval", "bridge"])
def test_stage_switches_are_spelled_alike(command, capsys):
    with pytest.raises(SystemExit) as done:
        main([command, "--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    assert "--safety, --no-safety" in text and "--mec, --no-mec" in text and "--docking, --no-docking" in text
    assert "on|off" not in text


@pytest.mark.parametrize("argv", [["scenarios", "--show", "paper-99"], ["train", "--config", "{bad"]])
def test_errors_go_to_stderr(argv, capsys):
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("error:")


@pytest.mark.parametrize("command", ["export", "train", "eval"])
def test_help_keeps_the_examples_of_the_command_docstring_on_their_own_lines(command, capsys):
    """Every command's --help prints its module docstring as written (its example lines intact)."""
    import importlib

    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = capsys.readouterr().out
    doc = importlib.import_module(f"stack.commands.{command}").__doc__
    first, *rest = [line for line in doc.strip().splitlines() if line.strip()]
    assert first in text
    assert all(line.rstrip() in text for line in rest[:4])


def test_a_command_imports_only_its_own_module():
    """`formation estop` (an operator stopping a fleet) and `formation --help` start without
    importing torch (~3 s): only the module of the command being run is imported."""
    import subprocess
    import sys

    code = ("import sys; from stack.cli import main\n"
            "for argv in ({argv}):\n"
            "    try: main(argv)\n"
            "    except SystemExit: pass\n"
            "print(sorted(m for m in ('torch', 'stack.commands.train', 'stack.commands.estop') if m in sys.modules))")
    def imported(*argvs: list[str]) -> str:
        done = subprocess.run([sys.executable, "-c", code.format(argv=", ".join(map(repr, argvs)) + ",")],
                              capture_output=True, text=True, check=True)
        return done.stdout.splitlines()[-1]

    assert imported(["--help"]) == "[]"
    assert imported(["estop", "--help"]) == "['stack.commands.estop']"
    assert imported(["train", "--help"]) == "['stack.commands.train', 'torch']"


def test_the_top_level_help_lists_every_command_with_its_line(capsys):
    from stack.cli import COMMANDS

    with pytest.raises(SystemExit) as done:
        main(["--help"])
    assert done.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for name, (_, line) in COMMANDS.items():
        assert f"{name} {line}" in text


def test_the_cli_exits_130_when_a_command_is_interrupted_inside_a_class_definition(monkeypatch, capsys):
    """A Ctrl-C inside an import reads as an interruption (sim.interrupts). The teeth: with
    ``except KeyboardInterrupt`` alone (the old rule) the RuntimeError escapes main() with a
    traceback."""
    monkeypatch.setattr(scenarios_command, "run", define_a_class_under_sigint)
    assert main(["scenarios"]) == 130
    assert capsys.readouterr().err.strip() == "interrupted"


def _alias_parser():
    import argparse

    from stack.commands.argtypes import add_deprecated_alias, positive

    parser = argparse.ArgumentParser(prog="x")
    parser.add_argument("--episode-ticks", type=positive, default=7)
    add_deprecated_alias(parser, "--steps", "--episode-ticks")
    parser.add_argument("--print-ticks", action="store_true")
    add_deprecated_alias(parser, "--trace", "--print-ticks", action="store_true")
    parser.add_argument("--record", default=None)
    add_deprecated_alias(parser, "--trace-dir", "--record", metavar="DIR")
    return parser


@pytest.mark.parametrize("old, new", [(["--steps", "5"], ["--episode-ticks", "5"]),
                                      (["--trace"], ["--print-ticks"]),
                                      (["--trace-dir", "d"], ["--record", "d"]),
                                      ([], [])])
def test_a_deprecated_alias_warns_and_parses_to_the_namespace_of_its_new_name(old, new, capsys):
    parser = _alias_parser()
    assert parser.parse_args(old) == parser.parse_args(new)
    err = capsys.readouterr().err
    if old:
        assert err == f"warning: {old[0]} is deprecated; use {new[0]}\n"
    else:
        assert err == ""


def test_a_deprecated_alias_is_hidden_from_help_and_checks_its_value_under_its_own_name(capsys):
    parser = _alias_parser()
    assert "--steps" not in parser.format_help() and "--trace" not in parser.format_help()
    with pytest.raises(SystemExit) as done:
        parser.parse_args(["--steps", "0"])
    assert done.value.code == 2
    assert "argument --steps: expected a positive integer, got 0" in capsys.readouterr().err


def _exit_and_stderr(argv: list[str], capsys) -> tuple[int, str]:
    """``formation ARGV``'s exit status (returned, or argparse's SystemExit) and its stderr."""
    try:
        code = main(argv)
    except SystemExit as done:
        code = done.code
    return code, capsys.readouterr().err


BRIDGE = ["bridge", "--fleet", "f", "--policy", "scripted"]
FLEET_SIM = ["fleet-sim", "--fleet", "f"]

BAD_VALUES = [   # (argv, what stderr must say): the flag as typed, and the value as typed
    ([*BRIDGE, "--stale-after", "0"], "argument --stale-after: expected seconds, a finite number > 0, got '0'"),
    ([*BRIDGE, "--estop-after", "nan"], "argument --estop-after: "),
    ([*BRIDGE, "--stale-after", "2"], "error: --stale-after 2 is longer than --estop-after 1"),
    ([*BRIDGE, "--ttl-ms", "0"], "argument --ttl-ms: expected an integer in 1..65535, got 0"),
    ([*BRIDGE, "--delay-percentile", "40"], "argument --delay-percentile: expected a percentile in [50, 100]"),
    ([*BRIDGE, "--delay-window", "1"], "argument --delay-window: expected an integer >= 8, got 1"),
    ([*BRIDGE, "--episode-ticks", "0"], "argument --episode-ticks: expected a positive integer, got 0"),
    ([*BRIDGE, "--command-delay-ms", "-5"], "argument --command-delay-ms: expected milliseconds, a finite "
                                             "number >= 0, got '-5'"),
    ([*FLEET_SIM, "--rate-hz", "0"], "argument --rate-hz: expected a rate in Hz, a finite number > 0, got '0'"),
    ([*FLEET_SIM, "--episodes", "0"], "argument --episodes: expected a positive integer, got 0"),
    ([*FLEET_SIM, "--lockstep-timeout", "-1"], "argument --lockstep-timeout: expected seconds"),
    ([*FLEET_SIM, "--start-timeout", "0"], "argument --start-timeout: expected seconds"),
    ([*FLEET_SIM, "--stop-after", "0"], "argument --stop-after: expected seconds"),
    ([*FLEET_SIM, "--brake-after-ticks", "0"], "argument --brake-after-ticks: expected a positive integer"),
    ([*FLEET_SIM, "--playout-ticks", "-1"], "argument --playout-ticks: expected an integer >= 0, got -1"),
    ([*FLEET_SIM, "--drop-commands", "2"], "argument --drop-commands: expected a probability in [0, 1), got '2'"),
    ([*FLEET_SIM, "--leave", "r9@3"], "error: --leave r9@3: paper-5 has robots r0, r1, r2, r3, r4"),
    ([*FLEET_SIM, "--join", "r7@1"], "error: --join r7@1: paper-5 has robots"),
    (["demo", "--fleet-episodes", "0"], "argument --fleet-episodes: expected a positive integer, got 0"),
    (["demo", "--episodes", "0"], "argument --episodes: expected a positive integer, got 0"),
    (["demo", "--budget-3", "-5"], "argument --budget-3: expected a positive integer, got -5"),
    (["certs", "--out", "certs", "--days", "0"], "argument --days: expected a positive integer, got 0"),
    (["eval", "--policy", "scripted", "--episodes", "0"], "argument --episodes: expected a positive integer"),
    (["eval", "--policy", "scripted", "--episode-ticks", "0"], "argument --episode-ticks: expected a positive"),
    (["eval", "--policy", "scripted", "--world", "pymunk", "--command-delay-ms", "-5"],
     "argument --command-delay-ms: expected milliseconds, a finite number >= 0, got '-5'"),
    (["plot", "some-run", "--episodes", "0"], "argument --episodes: expected an integer in 1..16, got 0"),
    (["plot", "some-run", "--step", "-1"], "argument --step: expected an integer >= 0, got -1"),
    (["sweep", "--episodes", "0"], "argument --episodes: expected a positive integer, got 0"),
    (["sweep", "--cpus", "0"], "argument --cpus: expected a positive integer, got 0"),
]


@pytest.mark.parametrize("argv, said", BAD_VALUES, ids=[" ".join(a[2:] if a[0] != "demo" else a) for a, _ in BAD_VALUES])
def test_a_bad_value_is_refused_naming_the_flag_typed_and_its_value(argv, said, capsys):
    """Before, these named config fields (stale_after_s, rate_hz, fleet-episodes, days, event
    (3, 'r9', 'leave')) or gave -5 ms back as -0.005."""
    code, err = _exit_and_stderr(argv, capsys)
    assert code == 2 and said in err and "Traceback" not in err, err


ALIASES = [   # (command line, the old spelling, the new one)
    (["eval", "--policy", "scripted"], ["--steps", "5"], ["--episode-ticks", "5"]),
    (["eval", "--policy", "scripted"], ["--json", "r.json"], ["--report", "r.json"]),
    (["eval", "--policy", "scripted"], ["--trace", "rec"], ["--record", "rec"]),
    (BRIDGE, ["--trace"], ["--print-ticks"]),
    (["demo"], ["--episodes", "3"], ["--fleet-episodes", "3"]),
    (["certs", "--out", "certs"], ["--robots", "a,b"], ["--robot-ids", "a,b"]),
    (["router", "--fleet", "f", "--certs", "c"], ["--robots", "a,b"], ["--robot-ids", "a,b"]),
]


@pytest.mark.parametrize("base, old, new", ALIASES, ids=[f"{b[0]} {o[0]}" for b, o, _ in ALIASES])
def test_every_deprecated_spelling_parses_as_its_new_one_and_warns(base, old, new, tmp_path, monkeypatch, capsys):
    from stack.cli import build_parser

    monkeypatch.chdir(tmp_path)
    parser = build_parser()
    assert parser.parse_args([*base, *old]) == parser.parse_args([*base, *new])
    assert capsys.readouterr().err == f"warning: {old[0]} is deprecated; use {new[0]}\n"
    with pytest.raises(SystemExit):
        main([base[0], "--help"])
    assert f"{old[0]} " not in capsys.readouterr().out.replace(new[0], "")


@pytest.mark.parametrize("base, switch", [(["router", "--fleet", "f", "--certs", "c"], "count"),
                                          (["train"], "stop"), (["train"], "tensorboard")])
def test_on_off_settings_take_both_spellings(base, switch, capsys):
    """Before, router had --no-count only, train --no-stop only and --tensorboard only."""
    from stack.cli import build_parser

    parser = build_parser()
    assert getattr(parser.parse_args([*base, f"--{switch}"]), switch) is True
    assert getattr(parser.parse_args([*base, f"--no-{switch}"]), switch) is False
    with pytest.raises(SystemExit):
        main([base[0], "--help"])
    assert f"--{switch}, --no-{switch}" in capsys.readouterr().out


def test_a_flag_given_overrides_the_config_files_boolean_both_ways(capsys):
    """train --no-tensorboard / --stop win over --config (flags given win, the docstring says);
    left out, the config's value stays."""
    import json

    config = '{"tensorboard": true, "stop_at_convergence": false}'
    assert main(["train", "--config", config, "--no-tensorboard", "--stop", "--print-config"]) == 0
    resolved = json.loads(capsys.readouterr().out)
    assert (resolved["tensorboard"], resolved["stop_at_convergence"]) == (False, True)
    assert main(["train", "--config", config, "--print-config"]) == 0
    resolved = json.loads(capsys.readouterr().out)
    assert (resolved["tensorboard"], resolved["stop_at_convergence"]) == (True, False)


@pytest.mark.parametrize("argv, said", [
    (["eval", "--policy", "scripted", "--recrod", "DIR", "--world", "pymunk"],
     "formation eval: error: unrecognized arguments: --recrod (did you mean --record?)"),
    (["eval", "--policy", "scripted", "--recrod", "--episods", "3"], "formation eval: error: unrecognized "
     "arguments: --recrod --episods (--recrod: did you mean --record?; --episods: did you mean --episodes?)"),
    (["train", "--no-tensorbaord"], "formation train: error: unrecognized arguments: --no-tensorbaord "
                                    "(did you mean --no-tensorboard?)"),
    (["bridge", "--fleet", "f", "--policy", "scripted", "--zzz"], "formation bridge: error: unrecognized "
                                                                  "arguments: --zzz\n"),
])
def test_an_unknown_option_is_reported_by_the_command_with_the_nearest_flag(argv, said, capsys):
    """Before: the top-level usage (`formation [-h] COMMAND ...`) and no word of the command."""
    code, err = _exit_and_stderr(argv, capsys)
    assert code == 2 and said in err
    assert err.startswith(f"usage: formation {argv[0]} ")


def test_formation_without_a_command_prints_its_usage_on_stderr(capsys):
    assert main([]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("usage: formation")


def test_every_duration_flag_shows_its_unit_and_every_flag_its_default(capsys):
    """Metavars S / MS / HZ instead of the dest's name, defaults stated (the report's 2.15)."""
    import re

    wanted = {"fleet-sim": ["--lockstep-timeout S", "--start-timeout S", "--rate-hz HZ", "--drop-commands P",
                            "(default 20.0)", "(default 30.0)"],
              "estop": ["--timeout S"], "router": ["--certs DIR", "--report FILE"],
              "bridge": ["--report FILE", "--ticks K"], "eval": ["--report FILE", "--record DIR"]}
    for command, texts in wanted.items():
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = re.sub(r"\s+", " ", capsys.readouterr().out)
        for piece in texts:
            assert piece in text, (command, piece)
    with pytest.raises(SystemExit):
        main(["fleet-sim", "--help"])
    text = re.sub(r"\s+", " ", capsys.readouterr().out)
    assert "--seed SEED seed of the first episode" in text


@pytest.mark.parametrize("argv", [["train", "--episode", "3"], ["eval", "--polic", "scripted"]])
def test_a_shortened_flag_is_refused_not_taken_for_the_one_it_begins(argv, capsys):
    """``train --episode 3`` used to run as ``--episodes 3``: a flag renamed or added later could
    then take a user's prefix over silently."""
    with pytest.raises(SystemExit) as done:
        main(argv)
    assert done.value.code == 2
    assert argv[1] in capsys.readouterr().err
