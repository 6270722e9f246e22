"""Link flags shared by the commands: ``--command-delay-ms`` (`formation eval`, `formation bridge`:
what the safety filter assumes of the link) and ``--model-error`` (`formation eval`,
`formation fleet-sim`: what the simulated robots and their link get wrong)."""

from __future__ import annotations

import argparse
import dataclasses
import json

from controllers.safety.latency import LatencyConfig, LatencyConfigError
from sim.pymunk_world import ModelError
from stack.commands.argtypes import milliseconds

MODEL_ERROR_FIELDS = {f.name for f in dataclasses.fields(ModelError)}
INT_FIELDS = ("delay_ticks", "delay_jitter_ticks", "playout_ticks")
MODEL_ERROR_HELP = ("FIELD=VALUE,... of sim.pymunk_world.ModelError, e.g. gain=0.7,lag_tau=0.05,"
                    "disturbance=0.1:0,delay_ticks=2,delay_jitter_ticks=1,state_drop=0.2,freeze=2:40,"
                    "playout_ticks=3,adaptive_playout=true (a JSON object of the same fields is accepted too)")


class LinkArgumentError(ValueError):
    """A bad link flag; the message names the flag and the fix."""

DEFAULT_COMMAND_DELAY_MS = 1000.0 * LatencyConfig().command_delay_s


def add_command_delay_arg(parser: argparse.ArgumentParser) -> None:
    """``--command-delay-ms MS`` (checked while parsing: a finite number >= 0, an error quotes the
    value as typed)."""
    parser.add_argument(
        "--command-delay-ms", type=milliseconds, default=DEFAULT_COMMAND_DELAY_MS, metavar="MS",
        help="bound on the time from sending a command to it acting on the robot (transport, "
             "actuation, jitter) that the safety filter predicts over and tightens for [ms] "
             f"(default {DEFAULT_COMMAND_DELAY_MS:g}: safe up to 150 ms without configuring "
             "anything; a user who knows their link can narrow it; a measured delay, if larger, wins)")


def latency_config(args: argparse.Namespace) -> LatencyConfig:
    """The LatencyConfig of ``--command-delay-ms`` (None: the default; ValueError naming the flag
    and the value as typed, in ms, on a bad value)."""
    ms = DEFAULT_COMMAND_DELAY_MS if args.command_delay_ms is None else args.command_delay_ms
    try:
        return LatencyConfig(command_delay_s=ms / 1000.0)
    except LatencyConfigError:
        raise ValueError(f"--command-delay-ms: expected milliseconds, a finite number >= 0, got {ms:g}") from None


def parse_model_error(text: str | None) -> ModelError:
    """``"gain=0.7,lag_tau=0.05,disturbance=0.1:0,freeze=2:40"`` (x:y for the pairs) or the same
    fields as a JSON object -> :class:`ModelError`; LinkArgumentError naming the field otherwise."""
    if not text or not text.strip():
        return ModelError()
    if text.strip().startswith("{"):
        try:
            fields = json.loads(text)
        except json.JSONDecodeError as exc:
            raise LinkArgumentError(f"--model-error: not a JSON object ({exc})") from None
        unknown = sorted(set(fields) - MODEL_ERROR_FIELDS) if isinstance(fields, dict) else None
        if unknown is None or unknown:
            raise LinkArgumentError(f"--model-error: unknown fields {unknown}; FIELD is one of "
                                    f"{sorted(MODEL_ERROR_FIELDS)}")
        return _model_error(fields)
    values: dict = {}
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or key not in MODEL_ERROR_FIELDS:
            raise LinkArgumentError(
                f"--model-error: {item!r} is not FIELD=VALUE with FIELD one of {sorted(MODEL_ERROR_FIELDS)}")
        try:
            if key in ("disturbance", "freeze"):
                x, _, y = raw.partition(":")
                values[key] = (float(x), float(y or 0.0)) if key == "disturbance" else (int(x), int(y))
            elif key in INT_FIELDS:
                values[key] = int(raw)
            elif key == "adaptive_playout":
                values[key] = {"true": True, "1": True, "false": False, "0": False}[raw.strip().lower()]
            else:
                values[key] = float(raw)
        except KeyError:
            raise LinkArgumentError(f"--model-error: {key}={raw!r}: write true or false") from None
        except ValueError:
            raise LinkArgumentError(f"--model-error: {key}={raw!r} is not a number"
                                    + (" (disturbance is X:Y in m/s^2)" if key == "disturbance" else "")
                                    + (" (freeze is ROBOT:TICK)" if key == "freeze" else "")) from None
    return _model_error(values)


def _model_error(fields: dict) -> ModelError:
    try:
        return ModelError(**fields)
    except (TypeError, ValueError) as exc:
        raise LinkArgumentError(f"--model-error: {exc}") from None
