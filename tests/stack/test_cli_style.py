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
