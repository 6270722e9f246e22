"""Settings, the stage book (``stages.json``) and child processes of a demo run.

``stages.json`` (rewritten atomically: temporary file + ``os.replace``)::

    format, version        "formation-stack/demo", 1
    settings               DemoSettings.to_dict() (a --resume reuses them)
    stages                 {name: {"done": true, "wall_s": s, "finished_unix": t, "result": {...}}}
                           for every finished stage, in the order of STAGES

A stage is written to the book only once all its files are in place, so a run stopped at
any moment keeps exactly the stages that finished; ``--resume`` skips them.

Child processes are started in their own process group (``start_new_session``); on Ctrl-C
(SIGINT), SIGTERM or SIGHUP (its terminal closed) :func:`interrupt_guard` sends SIGTERM to every
group, and :meth:`Children.terminate_all` waits for them and SIGKILLs what is left, so no process
outlives the demo. Should the demo die without that (SIGKILL), the kernel sends each child
SIGTERM (``PR_SET_PDEATHSIG``, Linux). While a demo runs it holds ``.demo.lock`` in its folder
(:func:`folder_lock`): a second demo on the same folder is refused.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sim.files import ConfigFileError, atomic_write_bytes, read_config

BOOK_FORMAT = "formation-stack/demo"
BOOK_VERSION = 1
BOOK_NAME = "stages.json"
LOCK_NAME = ".demo.lock"   # held by the running demo (folder_lock)
PR_SET_PDEATHSIG = 1       # <linux/prctl.h>
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
        """The book of the demo folder ``out`` (read with :func:`sim.files.read_config`, its types
        checked); DemoError naming the file and the fix for a missing, damaged or foreign one."""
        path = Path(out) / BOOK_NAME
        if not path.exists():
            raise DemoError(f"{str(path)!r} does not exist: --resume continues a demo folder written "
                            "by `formation demo --out DIR`; leave out --resume to start one")
        if not path.is_file():
            raise DemoError(f"{str(path)!r} is not a file: --resume continues a demo folder written "
                            "by `formation demo --out DIR`; start a new run in an empty --out")
        try:
            data = read_config(path, f"stage book {path}")
        except (ConfigFileError, OSError, UnicodeDecodeError) as exc:
            raise DemoError(f"{exc}; start a new run in an empty --out") from None
        if data.get("format") != BOOK_FORMAT or data.get("version") != BOOK_VERSION:
            raise DemoError(f"{str(path)!r} is not a {BOOK_FORMAT} v{BOOK_VERSION} stage book")
        settings, stages = data.get("settings"), data.get("stages", {})
        created = data.get("created_unix")
        if not isinstance(settings, dict):
            raise DemoError(f"{str(path)!r}: 'settings' is {'missing' if settings is None else 'not a mapping'}; "
                            "the book is damaged: start a new run in an empty --out")
        if not isinstance(stages, dict) or not all(
                isinstance(v, dict) and (not v.get("done") or isinstance(v.get("result"), dict))
                for v in stages.values()):
            raise DemoError(f"{str(path)!r}: 'stages' is not a mapping of stage records with their "
                            "results; the book is damaged: start a new run in an empty --out")
        unknown = sorted(set(stages) - set(STAGES))
        if unknown:
            raise DemoError(f"{str(path)!r} names unknown stages {unknown}")
        if created is not None and (isinstance(created, bool) or not isinstance(created, int | float)):
            raise DemoError(f"{str(path)!r}: 'created_unix' is not a number; the book is damaged")
        try:
            return cls(out, DemoSettings.from_dict(settings), stages, created)
        except TypeError as exc:
            raise DemoError(f"{str(path)!r}: its settings cannot be read ({exc})") from None

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


def _die_with_parent():
    """A ``preexec_fn`` that has the kernel send the child SIGTERM when this process ends
    (``prctl(PR_SET_PDEATHSIG)``, Linux): a child in its own session gets no SIGHUP from a closed
    terminal, and no signal at all when the demo is SIGKILLed. libc is looked up here, before
    the fork; the child only makes the call (and stops at once if the demo already ended)."""
    import ctypes

    prctl = ctypes.CDLL(None, use_errno=True).prctl
    parent = os.getpid()

    def preexec() -> None:
        prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM))
        if os.getppid() != parent:       # the demo died before the call: nobody to wait for
            os.kill(os.getpid(), signal.SIGTERM)

    return preexec


class Children:
    """Child processes of the demo, each the leader of its own process group."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def spawn(self, args: list[str], **kwargs: Any) -> subprocess.Popen:
        """Start ``args`` in its own process group; on Linux it gets SIGTERM when the demo dies,
        however it dies (SIGKILL included: :func:`_die_with_parent`)."""
        preexec = _die_with_parent() if sys.platform.startswith("linux") else None
        proc = subprocess.Popen(args, start_new_session=True, preexec_fn=preexec, **kwargs)
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


GUARDED_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""What stops a demo: Ctrl-C, a kill, and its terminal closing (SIGHUP)."""


@contextlib.contextmanager
def interrupt_guard(children: Children):
    """While active, SIGINT/SIGTERM/SIGHUP send SIGTERM to every child group and raise
    KeyboardInterrupt in the main thread (a second signal sends SIGKILL instead and returns)."""
    interrupted = {"count": 0}

    def handler(signum, frame):
        interrupted["count"] += 1
        if interrupted["count"] == 1:
            children.signal_all(signal.SIGTERM)
            raise KeyboardInterrupt
        children.signal_all(signal.SIGKILL)

    previous = {sig: signal.signal(sig, handler) for sig in GUARDED_SIGNALS}
    try:
        yield interrupted
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


@contextlib.contextmanager
def folder_lock(out: Path):
    """Hold an exclusive lock on ``out/.demo.lock`` (``fcntl.flock``) while the block runs: a
    second demo on the same folder (a ``--resume`` while one still runs) is refused with a
    DemoError instead of training beside it. The kernel drops the lock when this process
    ends, however it ends; the file stays (empty)."""
    import fcntl

    fd = os.open(Path(out) / LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise DemoError(f"another `formation demo` is running in {out} (it holds {LOCK_NAME}); "
                            "wait for it to end or stop it (Ctrl-C), then continue with --resume") from None
        yield
    finally:
        os.close(fd)
