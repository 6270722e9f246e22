"""Settings, the stage book (``stages.json``) and child processes of a demo run.

``stages.json`` (rewritten atomically: temporary file + ``os.replace``)::

    format, version        "formation-stack/demo", 1
    settings               DemoSettings.to_dict() (a --resume reuses them)
    stages                 {name: {"done": true, "wall_s": s, "finished_unix": t, "result": {...}}}
                           for every finished stage, in the order of STAGES

A stage is written to the book only once all its files are in place, so a run stopped at
any moment keeps exactly the stages that finished; ``--resume`` skips them.

Child processes are started in their own process group (``start_new_session``); on Ctrl-C
(SIGINT) or SIGTERM :func:`interrupt_guard` sends SIGTERM to every group, and
:meth:`Children.terminate_all` waits for them and SIGKILLs what is left, so no process
outlives the demo.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sim.files import atomic_write_bytes

BOOK_FORMAT = "formation-stack/demo"
BOOK_VERSION = 1
BOOK_NAME = "stages.json"
STAGES = ("train-3", "train-5", "generalist", "export", "fleet", "fleet-unseen", "report")


class DemoError(RuntimeError):
    """A demo that cannot go on; the message says what happened and what to do."""


@dataclass(frozen=True)
class DemoSettings:
    """What a demo run does (saved in ``stages.json``; ``--resume`` keeps them).

    Attributes:
        quick: the reduced run for CI (tiny budgets; everything else runs for real).
        seed: training seed; fleet episode k starts from seed + k.
        budget_3: episode cap of SDPA-MAPPO on paper-3: twice the paper's 1200, the budget
            ``bench/paper_tables.py`` gives. A cap, not a target: training stops at convergence
            and the report sets that episode beside the paper's; with the paper's own 1200 as
            the cap a slow seed reports nothing but "did not converge" (seed 0 on an AMD EPYC:
            0.00 at 1200 episodes, converged at 2112).
        budget_5: episode cap of the 5-robot transfer run: twice the paper's 850, as the bench.
        budget_generalist: episode cap of the generalist, one policy trained on 3, 4 and 5
            robots at once (the paper's single 5-robot run took 3200).
        eval_episodes, eval_interval: size and spacing of the convergence evaluations
            (None: the MAPPOConfig defaults, 100 episodes at least every 50).
        zero_shot_episodes: deterministic episodes of each zero-shot evaluation (the 3-robot
            policy on paper-5; the generalist on each team size of its table).
        fleet_episodes: pymunk episodes run over Zenoh through the ControlStack (each fleet stage).
    """

    quick: bool = False
    seed: int = 0
    budget_3: int = 2400
    budget_5: int = 1700
    budget_generalist: int = 3200
    eval_episodes: int | None = None
    eval_interval: int | None = None
    zero_shot_episodes: int = 100
    fleet_episodes: int = 5

    def __post_init__(self) -> None:
        for name in ("budget_3", "budget_5", "budget_generalist", "zero_shot_episodes", "fleet_episodes",
                     "eval_episodes", "eval_interval"):
            value = getattr(self, name)
            if value is None and name.startswith("eval_"):
                continue
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise DemoError(f"{name.replace('_', '-')} must be a positive integer, got {value!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise DemoError(f"seed must be an integer >= 0, got {self.seed!r}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DemoSettings:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise DemoError(f"{BOOK_NAME}: unknown settings {unknown}; was it written by a newer "
                            "version? Start a new run in an empty --out")
        return cls(**data)


FULL = DemoSettings()
QUICK = DemoSettings(quick=True, budget_3=32, budget_5=32, budget_generalist=32, eval_episodes=16,
                     eval_interval=16, zero_shot_episodes=16, fleet_episodes=2)


def jsonable(value: Any) -> Any:
    """``value`` with non-finite floats as None and numpy scalars as Python numbers."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, str | bytes):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_atomic(path: Path, text: str | bytes) -> None:
    """Write ``text`` to ``path`` atomically (:func:`sim.files.atomic_path`)."""
    atomic_write_bytes(path, text.encode() if isinstance(text, str) else text)


def write_json(path: Path, data: Any) -> None:
    write_atomic(path, json.dumps(jsonable(data), indent=2, allow_nan=False) + "\n")


class StageBook:
    """``stages.json`` of one demo folder (see the module docstring)."""

    def __init__(self, out: Path, settings: DemoSettings, stages: dict[str, dict] | None = None,
                 created_unix: float | None = None):
        self.out = Path(out)
        self.path = self.out / BOOK_NAME
        self.settings = settings
        self.stages: dict[str, dict] = dict(stages or {})
        self.created_unix = time.time() if created_unix is None else created_unix

    @classmethod
    def load(cls, out: Path) -> StageBook:
        path = Path(out) / BOOK_NAME
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise DemoError(f"{str(path)!r} does not exist: --resume continues a demo folder written "
                            "by `formation demo --out DIR`; leave out --resume to start one") from None
        except ValueError as exc:
            raise DemoError(f"{str(path)!r} is not valid JSON ({exc}); start a new run in an "
                            "empty --out") from None
        if data.get("format") != BOOK_FORMAT or data.get("version") != BOOK_VERSION:
            raise DemoError(f"{str(path)!r} is not a {BOOK_FORMAT} v{BOOK_VERSION} stage book")
        unknown = sorted(set(data.get("stages", {})) - set(STAGES))
        if unknown:
            raise DemoError(f"{str(path)!r} names unknown stages {unknown}")
        return cls(out, DemoSettings.from_dict(data["settings"]), data.get("stages"),
                   data.get("created_unix"))

    def done(self, name: str) -> bool:
        return bool(self.stages.get(name, {}).get("done"))

    def result(self, name: str) -> dict:
        if not self.done(name):
            raise DemoError(f"stage {name!r} has not finished; run the demo with --resume")
        return self.stages[name]["result"]

    def finish(self, name: str, result: dict, wall_s: float) -> None:
        """Mark ``name`` done with its result (a JSON-able dict) and save the book."""
        if name not in STAGES:
            raise ValueError(f"unknown stage {name!r}")
        self.stages[name] = {"done": True, "wall_s": round(wall_s, 3),
                             "finished_unix": round(time.time(), 3), "result": jsonable(result)}
        self.save()

    def save(self) -> None:
        ordered = {name: self.stages[name] for name in STAGES if name in self.stages}
        write_json(self.path, {"format": BOOK_FORMAT, "version": BOOK_VERSION,
                               "created_unix": self.created_unix,
                               "settings": self.settings.to_dict(), "stages": ordered})


class Children:
    """Child processes of the demo, each the leader of its own process group."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def spawn(self, args: list[str], **kwargs: Any) -> subprocess.Popen:
        proc = subprocess.Popen(args, start_new_session=True, **kwargs)
        self.procs.append(proc)
        return proc

    def signal_all(self, sig: int) -> None:
        """Send ``sig`` to the process group of every child still running (never raises)."""
        for proc in self.procs:
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(proc.pid, sig)

    def terminate_all(self, timeout_s: float = 15.0) -> None:
        """SIGTERM every group, wait up to ``timeout_s``, then SIGKILL what is left and reap."""
        self.signal_all(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for proc in self.procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        self.signal_all(signal.SIGKILL)
        for proc in self.procs:
            proc.wait()
        self.procs.clear()

    def forget(self, proc: subprocess.Popen) -> None:
        """Stop tracking a child that has exited and been reaped."""
        if proc in self.procs and proc.poll() is not None:
            self.procs.remove(proc)


@contextlib.contextmanager
def interrupt_guard(children: Children):
    """While active, SIGINT/SIGTERM send SIGTERM to every child group and raise
    KeyboardInterrupt in the main thread (a second signal sends SIGKILL instead and returns)."""
    interrupted = {"count": 0}

    def handler(signum, frame):
        interrupted["count"] += 1
        if interrupted["count"] == 1:
            children.signal_all(signal.SIGTERM)
            raise KeyboardInterrupt
        children.signal_all(signal.SIGKILL)

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield interrupted
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
