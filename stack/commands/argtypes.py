"""argparse types shared by the commands: a bad value exits 2 with the flag named, no traceback."""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path


def seed(text: str) -> int:
    """A seed: an integer in 0 .. 2**32 - 1 (numpy's seed range)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer seed >= 0, got {text!r}") from None
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"a seed must be in 0 .. 2**32 - 1, got {value}")
    return value


def _int_at_least(text: str, low: int, what: str) -> int:
    """``text`` as an integer >= ``low``; ArgumentTypeError saying ``what`` is expected."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"expected {what}, got {value}")
    return value


def positive(text: str) -> int:
    """A positive integer (a count)."""
    return _int_at_least(text, 1, "a positive integer")


def count(text: str) -> int:
    """An integer >= 0 (a number of ticks, episodes...)."""
    return _int_at_least(text, 0, "an integer >= 0")


def seconds(text: str) -> float:
    """A finite number of seconds >= 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds (a number >= 0), got {text!r}") from None
    if not (value >= 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds >= 0, got {text!r}")
    return value


def _number(text: str, what: str, ok=lambda value: True) -> float:
    """``text`` as a finite float for which ``ok`` holds; ArgumentTypeError saying ``what`` is
    expected (quoting ``text`` as typed) otherwise."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and ok(value)):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def positive_seconds(text: str) -> float:
    """A finite number of seconds > 0 (a timeout, a watchdog's delay)."""
    return _number(text, "seconds, a finite number > 0", lambda v: v > 0)


def milliseconds(text: str) -> float:
    """A finite number of milliseconds >= 0; an error quotes the value as typed, in ms."""
    return _number(text, "milliseconds, a finite number >= 0", lambda v: v >= 0)


def hertz(text: str) -> float:
    """A rate [Hz]: a finite number > 0."""
    return _number(text, "a rate in Hz, a finite number > 0", lambda v: v > 0)


def probability(text: str) -> float:
    """A probability in [0, 1) (1 would drop everything)."""
    return _number(text, "a probability in [0, 1)", lambda v: 0 <= v < 1)


def percentile(text: str) -> float:
    """A percentile in [50, 100] (a bound on a delay: the median or above)."""
    return _number(text, "a percentile in [50, 100]", lambda v: 50 <= v <= 100)


def int_range(low: int, high: int | None = None):
    """A type: an integer in ``low .. high`` (``high`` None: >= ``low``)."""
    what = f"an integer >= {low}" if high is None else f"an integer in {low}..{high}"

    def parse(text: str) -> int:
        value = _int_at_least(text, low, what)
        if high is not None and value > high:
            raise argparse.ArgumentTypeError(f"expected {what}, got {value}")
        return value

    parse.__name__ = f"int_range({low}, {high})"
    return parse


def lease_ms(text: str) -> int:
    """A Zenoh link lease [ms]: an integer >= 100 (what :class:`deploy.network.TransportConfig`
    takes; a shorter lease drops healthy links)."""
    return _int_at_least(text, 100, "milliseconds, an integer >= 100 (a shorter lease drops healthy links)")


def int_list(text: str) -> list[int]:
    """A comma-separated list of positive integers (``3,4,5``) or a range (``3-5``)."""
    try:
        if "-" in text and "," not in text:
            lo, hi = (int(x) for x in text.split("-"))
            values = list(range(lo, hi + 1))
        else:
            values = [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected integers like 3,4,5 or 3-5, got {text!r}") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers like 3,4,5 or 3-5, got {text!r}")
    return values


def _blocked_by_a_file(path: Path) -> str | None:
    """Why folders up to ``path`` cannot be made, or None: an ancestor that is a file, or the
    nearest existing folder not writable."""
    for parent in path.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                return f"{parent} is a file, not a folder; give a path under a folder"
            if not os.access(parent, os.W_OK | os.X_OK):
                return f"cannot create it in {parent} (permission denied); give a folder you can write to"
            return None
    return None


def out_folder(text: str) -> Path:
    """An output folder (``--out``): an existing folder or a path where one can be made; an
    existing file, or a path under one, is refused before any work starts."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{path}: exists and is not a folder; give a new folder "
                                         "or an existing one")
    if path.is_dir() and not os.access(path, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{path}: cannot write into this folder (permission denied); "
                                         "give a folder you can write to")
    problem = None if path.is_dir() else _blocked_by_a_file(path)
    if problem:
        raise argparse.ArgumentTypeError(f"{path}: {problem}")
    return path


def _new_path(text: str, what: str, example: str) -> Path:
    """``text`` as a path to write: not an existing folder (give ``what``, e.g. ``example`` in
    it), nor under a file; refused before any work starts."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{path}: is a folder; give {what}, e.g. {path / example}")
    problem = _blocked_by_a_file(path)
    if problem:
        raise argparse.ArgumentTypeError(f"{path}: {problem}")
    return path


def out_file(text: str) -> Path:
    """An output file (e.g. ``eval --report``): not an existing folder, nor under a file."""
    return _new_path(text, "a file name", "result.json")


def out_stem(text: str) -> Path:
    """An output stem (``export --out policy``: policy.onnx, policy.pt, ... beside each other):
    not an existing folder, nor under a file."""
    return _new_path(text, "a file stem in it", "policy")


INTRUDER_HELP = ("a disc the robots must keep clear of, seen by a tracker: radius=R,x=X,y=Y[,vx=VX,vy=VY]"
                 "[,enter=TICK][,leave=TICK][,max_speed=V] in m, m/s and ticks of each episode "
                 "(e.g. radius=0.06,x=0.5,y=1.1,vy=-0.2,enter=20: walks down from above the arena); "
                 "repeatable (sim.intruders.Intruder)")


def add_intruder_flag(parser: argparse.ArgumentParser, where: str = "") -> None:
    """``--intruder K=V,...`` (repeatable) -> ``args.intruder``: a list of sim.intruders.Intruder."""
    parser.add_argument("--intruder", type=_intruder, action="append", default=[], metavar="K=V,...",
                        help=INTRUDER_HELP + where)


def _intruder(text: str):
    from sim.intruders import Intruder

    try:
        return Intruder.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_stage_flags(parser: argparse.ArgumentParser, default: bool | None, where: str = "") -> None:
    """``--safety/--no-safety``, ``--mec/--no-mec`` and ``--docking/--no-docking``, the one
    spelling every command uses;
    ``default`` None leaves the choice to the command (``args.safety is None``: not given)."""
    state = "on" if default or default is None else "off"
    parser.add_argument("--safety", action=argparse.BooleanOptionalAction, default=default,
                        help=f"the barrier-QP safety filter{where} (default {state})")
    parser.add_argument("--mec", action=argparse.BooleanOptionalAction, default=default,
                        help=f"the Kalman model error compensator{where} (default {state})")
    parser.add_argument("--docking", action=argparse.BooleanOptionalAction, default=default,
                        help=f"the terminal mode that drives a robot near its free target onto "
                             f"it, through the filter{where} (default {state})")


def add_deprecated_alias(parser: argparse.ArgumentParser, old: str, new: str, **kwargs) -> None:
    """``old`` still works: it stores into ``new``'s dest and prints ``warning: OLD is deprecated;
    use NEW`` on stderr when given; hidden from --help.

    ``kwargs`` are :meth:`argparse.ArgumentParser.add_argument`'s (``action``, ``type``,
    ``nargs``...). Without them the alias takes the value the way ``new`` does (its action class,
    ``type``, ``nargs``, ``choices`` and ``metavar``, for a value-taking ``new`` added first). A bad
    value is reported under ``old``, the flag the user typed."""
    target = parser._option_string_actions.get(new)
    dest = kwargs.pop("dest", None) or (target.dest if target else new.lstrip("-").replace("-", "_"))
    if "action" not in kwargs and target is not None and isinstance(
            target, (argparse._StoreAction, argparse._AppendAction)):
        kwargs["action"] = type(target)
        for key in ("type", "nargs", "choices", "metavar"):
            kwargs.setdefault(key, getattr(target, key))
    action = kwargs.pop("action", "store")
    base = parser._registry_get("action", action, action)

    class DeprecatedAlias(base):
        def __call__(self, parser, namespace, values, option_string=None):
            print(f"warning: {option_string or old} is deprecated; use {new}", file=sys.stderr)
            super().__call__(parser, namespace, values, option_string)

    # default SUPPRESS: the alias never writes a default over the new flag's
    parser.add_argument(old, dest=dest, action=DeprecatedAlias, default=argparse.SUPPRESS,
                        help=argparse.SUPPRESS, **kwargs)


__all__ = ["add_deprecated_alias", "add_stage_flags", "count", "hertz", "int_list", "int_range", "milliseconds",
           "out_file", "out_folder", "out_stem", "percentile", "positive", "positive_seconds", "probability",
           "seconds", "seed", "seeds"]


def add_shared_clock_flag(parser: argparse.ArgumentParser, peers: str) -> None:
    """``--shared-clock/--no-shared-clock``: whether this node and its ``peers`` read one
    monotonic clock (one host); default: yes when every endpoint is on loopback."""
    parser.add_argument("--shared-clock", action=argparse.BooleanOptionalAction, default=None,
                        help=f"this node and the {peers} share one monotonic clock (one host): refuse "
                             "messages sent from the future and commands older than their ttl "
                             "(default: when every --listen/--connect endpoint is on loopback)")


def add_transport_flags(parser: argparse.ArgumentParser, identity: str) -> None:
    """``--listen``, ``--connect``, ``--certs``, ``--identity``, ``--insecure``: how a node joins
    the fleet's Zenoh network, the one spelling of ``bridge`` and ``fleet-sim``."""
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help="Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (peer mode; repeat for several)")
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                        help="Zenoh endpoint to connect to: a peer's, or with --certs the router's "
                             "tls/HOST:PORT (repeat for several)")
    parser.add_argument("--certs", default=None, metavar="DIR",
                        help="mutual TLS through `formation router` with this node's certificate from "
                             "DIR (`formation certs`); the node is then a client of the router")
    parser.add_argument("--identity", default=identity,
                        help=f"whose certificate of --certs this node presents (default {identity})")
    parser.add_argument("--insecure", action="store_true",
                        help="allow plain tcp links to endpoints off this host (a trusted network)")
    parser.add_argument("--zenoh-config", default=None, metavar="FILE",
                        help="a Zenoh configuration file (JSON5) as the base for any Zenoh setting; "
                             "the flags above are written over it where given")
    parser.add_argument("--lease-ms", type=lease_ms, default=None, metavar="MS",
                        help="Zenoh link lease: a frozen peer counts as gone after about this long "
                             "(default Zenoh's 10000)")


def transport_config(args: argparse.Namespace):
    """The :class:`deploy.network.TransportConfig` of :func:`add_transport_flags`' flags."""
    from deploy.certs import NodeFiles
    from deploy.network import TransportConfig

    if args.certs is None:
        return TransportConfig(listen=tuple(args.listen), connect=tuple(args.connect),
                               insecure=args.insecure, lease_ms=args.lease_ms,
                               zenoh_config=args.zenoh_config)
    if args.listen:
        raise ValueError("--listen with --certs: a client of the router listens nowhere; "
                         "give the router's endpoint with --connect tls/HOST:PORT")
    return TransportConfig(connect=tuple(args.connect), mode="client", lease_ms=args.lease_ms,
                           tls=NodeFiles.in_dir(args.certs, args.identity), zenoh_config=args.zenoh_config)


def seeds(text: str) -> list[int]:
    """``--seeds``: ``5`` -> 0..4; ``2-4`` -> 2, 3, 4; ``0,3,7`` -> those (``0,`` -> seed 0 alone)."""
    try:
        if "," in text:
            values = [int(s) for s in text.split(",") if s.strip()]
        elif "-" in text.strip()[1:]:
            lo, hi = (int(s) for s in text.split("-", 1))
            values = range(lo, hi + 1)
        else:
            values = range(int(text))
        if len(values) > _MAX_SEEDS:
            raise argparse.ArgumentTypeError(f"at most {_MAX_SEEDS} seeds, got {text!r}")
        values = list(values)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a count (5), a range (2-4) or a list (0,3,7), "
                                         f"got {text!r}") from None
    if not values:
        raise argparse.ArgumentTypeError(f"a count of seeds must be >= 1, got {text!r} (seed 0 alone: --seeds 0,)")
    if min(values) < 0 or len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"seeds must be distinct and >= 0, got {text!r}")
    if max(values) >= 2**32:
        raise argparse.ArgumentTypeError(f"a seed must be in 0 .. 2**32 - 1, got {text!r}")
    return values


_MAX_SEEDS = 100_000
