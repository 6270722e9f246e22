"""The latency flag shared by `formation eval` and `formation bridge`: what the safety filter assumes of the link."""

from __future__ import annotations

import argparse

from controllers.safety.latency import LatencyConfig, LatencyConfigError

DEFAULT_COMMAND_DELAY_MS = 1000.0 * LatencyConfig().command_delay_s


def add_command_delay_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--command-delay-ms", type=float, default=DEFAULT_COMMAND_DELAY_MS, metavar="MS",
        help="bound on the time from sending a command to it acting on the robot (transport, "
             "actuation, jitter) that the safety filter predicts over and tightens for [ms] "
             f"(default {DEFAULT_COMMAND_DELAY_MS:g}: safe up to 150 ms without configuring "
             "anything; a user who knows their link can narrow it; a measured delay, if larger, wins)")


def latency_config(args: argparse.Namespace) -> LatencyConfig:
    """The LatencyConfig of ``--command-delay-ms`` (ValueError naming the flag on a bad value)."""
    try:
        return LatencyConfig(command_delay_s=args.command_delay_ms / 1000.0)
    except LatencyConfigError as exc:
        raise ValueError(f"--command-delay-ms: {exc}") from None
