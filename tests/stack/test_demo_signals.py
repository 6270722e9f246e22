"""No process outlives `formation demo`, and one demo runs in a folder at a time: its terminal
closing (SIGHUP) stops it like Ctrl-C, its children die with it however it dies (Linux), and a
second demo on a folder in use is refused (stack.demo.state)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from stack.cli import main
from stack.demo.state import DemoSettings, StageBook, folder_lock

ROOT = Path(__file__).resolve().parents[2]
SLEEPER = (f"[{sys.executable!r}, '-c', 'import time; time.sleep(60)'], "
           "stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL")   # not holding the test's pipes


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for its reaper counts as ended)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in ("Z", "X")


def _script(code: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


@contextlib.contextmanager
def _reaping(pids: list[int]):
    """Kill (by id) whatever of ``pids`` a failing test left running."""
    try:
        yield
    finally:
        for pid in pids:
            if _alive(pid):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)


def test_sighup_stops_the_demo_and_its_children_like_ctrl_c():
    """The guard turns SIGHUP into the interrupt SIGINT is: children get SIGTERM, exit code 130.
    Without it SIGHUP kills the demo and its children (own sessions) run on."""
    done = _script(f"""
        import os, signal, subprocess, sys, time
        from stack.demo.state import Children, interrupt_guard
        children = Children()
        with interrupt_guard(children):
            try:
                child = children.spawn({SLEEPER})
                print(child.pid, flush=True)
                os.kill(os.getpid(), signal.SIGHUP)
                time.sleep(30)
            except KeyboardInterrupt:
                children.terminate_all()
                print("interrupted", child.returncode, flush=True)
                sys.exit(130)
    """)
    lines = done.stdout.split()
    with _reaping([int(lines[0])] if lines else []):
        assert done.returncode == 130, (done.returncode, done.stderr)
        assert lines[1:] == ["interrupted", str(-signal.SIGTERM)]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_child_ends_when_the_demo_dies_without_cleaning_up():
    """The demo SIGKILLed (no handler runs): the kernel sends its child SIGTERM."""
    done = _script(f"""
        import os, subprocess
        from stack.demo.state import Children
        child = Children().spawn({SLEEPER})
        print(child.pid, flush=True)
        os._exit(0)
    """)
    child = int(done.stdout.split()[0])
    with _reaping([child]):
        deadline = time.monotonic() + 10
        while _alive(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(child)


def test_a_second_demo_on_a_folder_in_use_is_refused(tmp_path, capsys, monkeypatch):
    """While a demo holds the folder (its lock), `demo --resume` on it starts nothing: exit 2."""
    import stack.commands.demo as demo_command

    StageBook(tmp_path, DemoSettings(budget_3=8)).save()
    monkeypatch.setattr(demo_command, "run_stage", lambda *a: pytest.fail("a stage ran"))
    with folder_lock(tmp_path):
        assert main(["demo", "--out", str(tmp_path), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: another `formation demo` is running in {tmp_path}")
    with folder_lock(tmp_path):      # the lock goes with its holder
        pass
