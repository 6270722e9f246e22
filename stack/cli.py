"""``formation``: the command line of formation-stack.

Each subcommand lives in its own module under :mod:`stack.commands` and exposes
``register(subparsers)``, which adds its parser and sets ``func`` to the handler
``func(args) -> int`` (the exit code).
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMAND_MODULES = [
    "stack.commands.scenarios",
    "stack.commands.demo",
    "stack.commands.export",
    "stack.commands.fleet_sim",
    "stack.commands.bridge",
    "stack.commands.certs",
    "stack.commands.estop",
    "stack.commands.router",
    "stack.commands.eval",
    "stack.commands.train",
    "stack.commands.sweep",
    "stack.commands.plot",
]

DESCRIPTION = """\
formation-stack: SDPA-MAPPO formation change for cooperative multi-robot transport,
carried to robots through a safety layer (FCL + OSQP barrier QP), a Kalman model error
compensator and a Zenoh fleet bridge.

Start with `formation scenarios` to see the task presets.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="formation", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    add_parser = sub.add_parser

    def add_command(name: str, **kwargs) -> argparse.ArgumentParser:
        # each command's description is its module docstring: keep its lines and examples
        kwargs.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)
        return add_parser(name, **kwargs)

    sub.add_parser = add_command
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
