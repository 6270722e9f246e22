"""One module per `formation` subcommand (see stack.cli)."""
