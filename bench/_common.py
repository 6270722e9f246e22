"""Shared helpers of the benchmark scripts: thread set-up, timing, progress, table and JSON output.

Every benchmark prints a human-readable table by default and, with ``--json``, exactly one JSON
document on stdout; progress lines always go to stderr so that ``--json`` output can be piped.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from sim.provenance import git_commit
from sim.scenario import MAX_ROBOTS
from stack.commands import argtypes

GIT_AT_START = git_commit()

L_OBJECT = ((0.4, 0.35), (0.6, 0.35), (0.6, 0.45), (0.5, 0.45), (0.5, 0.65), (0.4, 0.65))
"""An L-shaped, non-convex object cut from the presets' 0.2 x 0.3 box (its re-entrant corner at
(0.5, 0.45)): the held-out layout of ``generalization.py`` and an object condition of ``safety.py``."""
"""The checkout when the benchmark started: the code that ran. A long run outlives commits and
edits made beside it; what its document records is this, with the checkout at the end beside
it (``git_at_end``) when they differ."""


def bounded_int(text: str, minimum: int = 1, maximum: int | None = None) -> int:
    """A single integer in ``minimum..maximum`` (no upper bound when ``maximum`` is None)."""
    kind = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
    if maximum is not None:
        kind = f"an integer in {minimum}..{maximum}"
    item = text.strip()
    if not item.isdigit() or int(item) < minimum or (maximum is not None and int(item) > maximum):
        raise argparse.ArgumentTypeError(f"{text!r} is not {kind}")
    return int(item)


def int_list(text: str, minimum: int = 1, maximum: int | None = None) -> list[int]:
    """``"1,64,1024"`` -> ``[1, 64, 1024]``; every item must be an integer in ``minimum..maximum``
    (no upper bound when ``maximum`` is None)."""
    items = [part.strip() for part in text.split(",") if part.strip()]
    if not items:
        raise argparse.ArgumentTypeError(f"expected a comma-separated list of integers >= {minimum}, got {text!r}")
    return [bounded_int(item, minimum, maximum) for item in items]


def positive_int_list(text: str) -> list[int]:
    """argparse type: ``"1,64,1024"`` -> ``[1, 64, 1024]``; every item must be a positive integer."""
    return int_list(text, 1)


def nonnegative_int_list(text: str) -> list[int]:
    """argparse type: ``"0,25,100"`` -> ``[0, 25, 100]``; every item must be an integer >= 0."""
    return int_list(text, 0)


def robot_count_list(text: str) -> list[int]:
    """argparse type of ``--robots``: ``"3,5"`` -> ``[3, 5]``; every item a team size the scenarios
    can place, 1..:data:`sim.scenario.MAX_ROBOTS`."""
    return int_list(text, 1, MAX_ROBOTS)


def positive_int(text: str) -> int:
    """argparse type: a single positive integer."""
    return bounded_int(text, 1)


def nonnegative_int(text: str) -> int:
    """argparse type: a single integer >= 0."""
    return bounded_int(text, 0)


def robot_count(text: str) -> int:
    """argparse type of a single ``--robots``: 1..:data:`sim.scenario.MAX_ROBOTS`."""
    return bounded_int(text, 1, MAX_ROBOTS)


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (``nan`` and ``inf`` are refused)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def json_object(text: str) -> dict:
    """argparse type: a JSON object, e.g. ``'{"update_epochs": 4, "actor": {"token_layers": 1}}'``."""
    try:
        value = json.loads(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected a JSON object, got {text!r} ({err})") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object such as '{{\"update_epochs\": 4}}', got {text!r}")
    return value


def add_output_args(parser: argparse.ArgumentParser) -> None:
    """``--json`` and ``--threads``, the options every benchmark shares."""
    parser.add_argument("--json", action="store_true",
                        help="print one JSON document on stdout instead of the table")
    parser.add_argument("--threads", type=positive_int, default=1,
                        help="torch intra-op threads for every measured run (default: 1, the "
                             "stable choice on a shared machine; the value is printed and saved)")


def add_tick_args(parser: argparse.ArgumentParser, per: str) -> None:
    """``--robots``, ``--ticks``, ``--warmup`` and ``--seed`` of the control-tick benchmarks
    (``per``: what each timed run is, e.g. "stack")."""
    parser.add_argument("--robots", type=robot_count, default=5,
                        help=f"robots in the fleet, 1..{MAX_ROBOTS} (default 5)")
    parser.add_argument("--ticks", type=positive_int, default=2000, help=f"timed ticks per {per} (default 2000)")
    parser.add_argument("--warmup", type=positive_int, default=100, help=f"untimed ticks per {per} (default 100)")
    add_seed_arg(parser, "the untrained actor and of the states it is timed on")


def add_seed_arg(parser: argparse.ArgumentParser, what: str, default: int = 0) -> None:
    """``--seed`` of a benchmark: one seed in 0 .. 2**32 - 1 (:func:`stack.commands.argtypes.seed`,
    the spelling of every ``formation`` command); ``what`` says what it seeds."""
    parser.add_argument("--seed", type=argtypes.seed, default=default,
                        help=f"seed of {what}, 0 .. 2**32 - 1 (default {default})")


def p50_p99(values: Sequence[float]) -> dict[str, float]:
    """``{"p50", "p99"}`` percentiles of ``values``."""
    return {"p50": float(np.percentile(values, 50)), "p99": float(np.percentile(values, 99))}


def set_threads(threads: int) -> int:
    """Set torch's intra-op thread count and return the value torch reports back."""
    torch.set_num_threads(threads)
    return torch.get_num_threads()


def progress(message: str) -> None:
    """One progress line on stderr (stdout is reserved for the result)."""
    print(message, file=sys.stderr, flush=True)


def median_rates(steppers: dict[str, Callable[[int], Any]], *, steps: int, repeats: int,
                 warmup: int, items_per_call: int) -> dict[str, float]:
    """Median over ``repeats`` timed runs of ``items_per_call * steps / seconds`` for each stepper.

    ``step(k)`` performs one call (``k`` counts that stepper's calls from 0, for cycling a bank
    of inputs). Each stepper first gets ``warmup`` untimed calls; then the repeats are
    interleaved (repeat 1 of every stepper, then repeat 2, ...) so that a change of machine load
    during the run affects all of them alike. Returns items per second (e.g. env-steps/s).
    """
    if steps < 1 or repeats < 1 or warmup < 0:
        raise ValueError(f"steps and repeats must be >= 1 and warmup >= 0, got "
                         f"steps={steps}, repeats={repeats}, warmup={warmup}")
    calls = dict.fromkeys(steppers, 0)
    for name, step in steppers.items():
        for _ in range(warmup):
            step(calls[name])
            calls[name] += 1
    rates: dict[str, list[float]] = {name: [] for name in steppers}
    for _ in range(repeats):
        for name, step in steppers.items():
            k0 = calls[name]
            start = time.perf_counter()
            for k in range(k0, k0 + steps):
                step(k)
            elapsed = time.perf_counter() - start
            calls[name] = k0 + steps
            rates[name].append(items_per_call * steps / max(elapsed, 1e-12))
    return {name: statistics.median(values) for name, values in rates.items()}


def format_rate(value: float) -> str:
    """Readable rate: ``1234567.0`` -> ``'1.23M'``."""
    if not math.isfinite(value):
        return "-"
    for scale, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(value) >= scale:
            return f"{value / scale:.3g}{suffix}"
    return f"{value:.3g}"


def print_table(headers: Sequence[str], rows: Sequence[Sequence[Any]], file=None) -> None:
    """Print ``rows`` under ``headers`` as aligned columns (right-aligned except the first)."""
    file = file if file is not None else sys.stdout
    cells = [[str(h) for h in headers]] + [[str(c) for c in row] for row in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(headers))]

    def line(row: Sequence[str]) -> str:
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w)
                         for i, (c, w) in enumerate(zip(row, widths, strict=True)))

    print(line(cells[0]), file=file)
    print("  ".join("-" * w for w in widths), file=file)
    for row in cells[1:]:
        print(line(row), file=file)


def print_json(document: dict[str, Any], *, provenance: bool = True) -> None:
    """The result document on stdout, one line, nothing else; it gains a ``provenance`` entry
    (:func:`sim.provenance.provenance`: git commit, package versions, threads, host, command line)
    unless it holds one, so every saved result says what code and packages made it: the git
    entry is :data:`GIT_AT_START`, the checkout's state at the end ``git_at_end`` if it changed.
    ``provenance=False`` for a document whose top-level keys are data that tools iterate over."""
    if provenance and "provenance" not in document:
        from sim.provenance import provenance as record

        made = record()
        if made["git"] != GIT_AT_START:
            made = {**made, "git": GIT_AT_START, "git_at_end": made["git"]}
        document = {**document, "provenance": made}
    print(json.dumps(document), flush=True)


def map_episodes(fn: Callable[[Any], dict], tasks: Sequence[Any], workers: int, desc: str,
                 chunksize: int = 2) -> list[dict]:
    """``fn`` over ``tasks`` with a progress bar on stderr: in ``workers`` forked processes
    (results in completion order) or, with one worker, in this process."""
    import multiprocessing

    from tqdm import tqdm

    rows = []
    with tqdm(total=len(tasks), desc=desc, unit="ep", file=sys.stderr) as bar:
        if workers > 1:
            with multiprocessing.get_context("fork").Pool(workers) as pool:
                for row in pool.imap_unordered(fn, tasks, chunksize=chunksize):
                    rows.append(row)
                    bar.update()
        else:
            for task in tasks:
                rows.append(fn(task))
                bar.update()
    return rows
