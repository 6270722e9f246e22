"""``formation``: the command line of formation-stack.

Each subcommand lives in its own module under :mod:`stack.commands` and exposes
``register(subparsers)``, which adds its parser (its one-line help comes from :data:`COMMANDS`)
and sets ``func`` to the handler ``func(args) -> int`` (the exit code). Only the module of the
command being run is imported.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import sys
from collections.abc import Collection

from sim.interrupts import caused_by_interrupt

COMMANDS: dict[str, tuple[str, str]] = {
    "scenarios": ("stack.commands.scenarios", "list the scenario presets (or show one with --show NAME)"),
    "demo": ("stack.commands.demo", "train, transfer, export and run a fleet over Zenoh; write a report"),
    "export": ("stack.commands.export", "export a trained actor as verified policy files"),
    "fleet-sim": ("stack.commands.fleet_sim", "run the pymunk world as robots over Zenoh"),
    "bridge": ("stack.commands.bridge", "run the controller of a fleet over Zenoh"),
    "certs": ("stack.commands.certs", "make the fleet CA and node certificates (mutual TLS)"),
    "estop": ("stack.commands.estop", "engage, release or query a running bridge's fleet e-stop"),
    "router": ("stack.commands.router", "run the fleet's Zenoh router (mutual TLS, access control)"),
    "eval": ("stack.commands.eval", "evaluate a checkpoint, an exported policy or the scripted controller"),
    "train": ("stack.commands.train", "train a policy (SDPA-MAPPO by default) on a scenario"),
    "sweep": ("stack.commands.sweep", "train a grid of configs x seeds on Ray Tune"),
    "plot": ("stack.commands.plot", "plot training curves, trajectories and attention of runs as PNG"),
}
"""Subcommand -> (its module, its one-line help). :func:`main` imports only the module of the
command it runs: most import torch (~3 s), and an operator's ``formation estop --engage`` should
not wait for that."""

DESCRIPTION = """\
formation-stack: SDPA-MAPPO formation change for cooperative multi-robot transport,
carried to robots through a safety layer (FCL + OSQP barrier QP), a Kalman model error
compensator and a Zenoh fleet bridge.

Start with `formation scenarios` to see the task presets.
"""


def build_parser(full: Collection[str] = tuple(COMMANDS)) -> argparse.ArgumentParser:
    """The ``formation`` parser; the commands named in ``full`` (default: every one) get their
    options in full (their modules imported), the others their one-line help only."""
    parser = argparse.ArgumentParser(prog="formation", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    add_parser = sub.add_parser

    def add_command(name: str, **kwargs) -> argparse.ArgumentParser:
        # each command's description is its module docstring: keep its lines and examples
        kwargs.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)
        kwargs.setdefault("allow_abbrev", False)   # a flag renamed later must not take over a prefix
        return add_parser(name, help=COMMANDS[name][1], **kwargs)

    sub.add_parser = add_command
    for name, (module, _) in COMMANDS.items():
        if name in full:
            importlib.import_module(module).register(sub)
        else:
            add_command(name, add_help=False)
    return parser


def _named_command(argv: list[str]) -> tuple[str, ...]:
    """The subcommand ``argv`` names (the first word that is not an option), if it is one."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return (word,) if word in COMMANDS else ()


def _command_parser(parser: argparse.ArgumentParser, name: str | None) -> argparse.ArgumentParser:
    """The sub-parser of command ``name`` (the top-level parser when there is none)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and name in action.choices:
            return action.choices[name]
    return parser


def _unknown_words(parser: argparse.ArgumentParser, extra: list[str]) -> str:
    """"unrecognized arguments: ..." with the nearest option of ``parser`` for each unknown one."""
    options = sorted({option for action in parser._actions if action.help != argparse.SUPPRESS
                      for option in action.option_strings})
    hints = {}
    for word in extra:
        if word.startswith("-"):
            near = difflib.get_close_matches(word.partition("=")[0], options, n=1, cutoff=0.7)
            if near:
                hints[word] = f"did you mean {near[0]}?"
    if len(extra) == 1 and hints:
        return f"unrecognized arguments: {extra[0]} ({hints[extra[0]]})"
    said = "; ".join(f"{word}: {hint}" for word, hint in hints.items())
    return f"unrecognized arguments: {' '.join(extra)}" + (f" ({said})" if said else "")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(_named_command(argv))
    args, extra = parser.parse_known_args(argv)
    if extra:   # said by the command's own parser, with its usage (argparse would use the top level's)
        command = _command_parser(parser, getattr(args, "command", None))
        command.error(_unknown_words(command, extra))
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except BaseException as exc:
        if not caused_by_interrupt(exc):
            raise
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
