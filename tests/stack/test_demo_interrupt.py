"""Ctrl-C during the fleet stage of `formation demo`, and during train-5 while the generalist
trains in a child process: every child process stops cleanly, finished stages are kept, and
`--resume` finishes the run from there.

Each run starts from a copy of the quick demo's folder (``quick_run``) cut back: for the fleet
test to its trained (generalist included) and exported stages, with four fleet episodes (a
window wide enough to interrupt mid-run), so the demo resumes straight into the fleet stage and
the test trains nothing itself; for the train-5 test to train-3 alone, and what it resumes is the
interrupted background training (the stages after it are the fleet test's)."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from stack.cli import main
from stack.demo.report import save_metrics
from stack.demo.stages import run_dir, train_stage
from stack.demo.state import STAGES, StageBook
from tests.stack.conftest import QUICK_BUDGET
from tests.xdist_groups import DEMO

# With the quick demo's worker (test_demo.py). The SIGINT waits for the moment it needs (files and
# processes), not for the clock, and the fleet runs lock-stepped.
pytestmark = DEMO

LEARNED = ("train-3", "train-5", "generalist", "export")
FLEET_EPISODES = 4   # the SIGINT comes once the first has ended: three left to interrupt

ROOT = Path(__file__).resolve().parents[2]
WAIT_S = 300.0


def processes_naming(text: str, exclude: int) -> dict[int, list[str]]:
    """Live processes (other than ``exclude``) whose command line contains ``text``."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == exclude:
            continue
        try:
            args = (entry / "cmdline").read_bytes().decode(errors="replace").split("\0")
        except OSError:
            continue
        if any(text in a for a in args):
            found[int(entry.name)] = args
    return found


def trained_copy(finished: Path, out: Path, keep: tuple[str, ...] = LEARNED, drop: tuple[str, ...] = (),
                 **settings_changed) -> None:
    """``out``: the demo folder ``finished`` as it was when its stages ``keep`` had ended (the
    folders ``drop`` removed), its settings changed as ``settings_changed`` says (fields of
    :class:`stack.demo.state.DemoSettings`)."""
    shutil.copytree(finished, out, ignore=shutil.ignore_patterns("fleet", "report.*", "*.png", *drop))
    done = StageBook.load(out)
    settings = dataclasses.replace(done.settings, **settings_changed)
    book = StageBook(out, settings, {name: done.stages[name] for name in keep}, done.created_unix)
    book.save()
    save_metrics(book, complete=False)


def interrupt_resumed_demo(out: Path, log_path: Path, ready) -> dict[int, list[str]]:
    """Run ``formation demo --resume --out OUT`` in a child process until ``ready(demo_pid)``
    returns the processes it waits for (not None), then SIGINT it; it must exit with 130.
    Returns those processes."""
    with log_path.open("w") as log:
        demo = subprocess.Popen([sys.executable, "-m", "stack.cli", "demo", "--resume", "--out", str(out)],
                                cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + WAIT_S
            found = None
            while found is None and time.monotonic() < deadline:
                assert demo.poll() is None, log_path.read_text()
                found = ready(demo.pid)
                time.sleep(0.05)
            assert found is not None, f"not ready within {WAIT_S} s:\n{log_path.read_text()}"
            os.kill(demo.pid, signal.SIGINT)
            assert demo.wait(timeout=120) == 130, log_path.read_text()
        finally:
            if demo.poll() is None:
                demo.kill()
                demo.wait()
    return found


def test_sigint_in_the_fleet_stage_stops_everything_and_resume_finishes(tmp_path, quick_run):
    out = tmp_path / "run"
    trained_copy(quick_run, out, fleet_episodes=FLEET_EPISODES)

    def fleet_mid_run(demo_pid: int) -> dict | None:   # both fleet processes up, one episode finished
        children = processes_naming(str(out), exclude=demo_pid)
        sim_log = out / "fleet" / "sim.log"
        if len(children) == 2 and sim_log.is_file() and '"episode": 0' in sim_log.read_text():
            return children
        return None

    children = interrupt_resumed_demo(out, tmp_path / "demo.log", fleet_mid_run)
    commands = sorted(" ".join(args) for args in children.values())
    assert len(commands) == 2 and "bridge" in commands[0] and "fleet-sim" in commands[1], commands
    assert processes_naming(str(out), exclude=os.getpid()) == {}   # no orphans (the demo has exited)
    assert "formation demo --out" in (tmp_path / "demo.log").read_text()   # tells how to resume

    book = json.loads((out / "stages.json").read_text())
    assert list(book["stages"]) == list(LEARNED)
    partial = json.loads((out / "metrics.json").read_text())
    assert partial["complete"] is False and set(partial["train"]) == {"3", "5", "generalist"}
    assert partial["export"]["verified"] is True and "fleet" not in partial
    # Both children took their clean path on SIGTERM: they wrote their reports on the way out.
    sim = json.loads((out / "fleet" / "sim.json").read_text())
    assert 1 <= len(sim["episodes"]) < FLEET_EPISODES
    assert (out / "fleet" / "bridge.json").is_file()

    assert main(["demo", "--out", str(out), "--resume"]) == 0
    finished = json.loads((out / "stages.json").read_text())
    assert list(finished["stages"]) == list(STAGES)
    for name in LEARNED:   # kept, not redone
        assert finished["stages"][name] == book["stages"][name]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["complete"] is True and metrics["fleet"]["episodes"] == FLEET_EPISODES
    assert metrics["fleet_unseen"]["episodes"] == FLEET_EPISODES
    assert len(metrics["fleet"]["per_episode"]) == FLEET_EPISODES
    assert (out / "report.html").is_file() and (out / "report.md").is_file()


def test_sigint_in_train_5_stops_the_generalists_background_training_too(tmp_path, quick_run):
    out = tmp_path / "run"
    # train-5 keeps the quick demo's 32 episodes: the SIGINT must land while it still trains
    trained_copy(quick_run, out, keep=("train-3",), fleet_episodes=2, budget_5=32,
                 drop=("train-5", "train-generalist", "generalist", "fleet-unseen", "policy.*"))

    def generalist_training(demo_pid: int) -> dict | None:   # its child trains beside train-5
        child = processes_naming("stack.demo.stages", exclude=demo_pid)
        return child if child and (out / "train-generalist" / "train.jsonl").is_file() else None

    child = interrupt_resumed_demo(out, tmp_path / "demo.log", generalist_training)
    assert len(child) == 1 and str(out) in next(iter(child.values())), child
    assert processes_naming(str(out), exclude=os.getpid()) == {}   # the background training too
    assert list(json.loads((out / "stages.json").read_text())["stages"]) == ["train-3"]

    # The resume restarts this very child (stack.demo.stages OUT: train_stage on the same folder)
    # beside train-5; run here, it must take up the interrupted run and finish it to its budget.
    # That the demo's --resume then runs every later stage is the fleet test's part.
    interrupted = run_dir(out, "generalist")
    had_checkpoint = (interrupted / "checkpoint.pt").is_file()
    before = (interrupted / "train.jsonl").read_text().splitlines() if had_checkpoint else []
    train_stage(StageBook.load(out).settings, "generalist", out)
    assert json.loads((interrupted / "result.json").read_text())["episodes"] >= QUICK_BUDGET
    rows = (interrupted / "train.jsonl").read_text().splitlines()
    iterations = [json.loads(row)["iteration"] for row in rows]
    assert iterations == list(range(1, len(iterations) + 1))   # one curve
    # continued, not started afresh: a fresh start would rewrite the first row's wall_time_s (rows
    # after the checkpoint are dropped and run again, so only the first is compared)
    if had_checkpoint:
        assert rows[0] == before[0]
