"""Run FCL queries in a child process: on some touching shapes FCL's EPA throws a C++
``std::logic_error`` that python-fcl does not catch, and the process aborts (SIGABRT). A test
that asks in a child fails on that instead of killing the whole test run."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[3]


def run_child(code: str, timeout_s: float = 120.0) -> Any:
    """Run ``code`` (dedented) in a fresh interpreter at the repository root; the JSON its
    stdout holds. AssertionError with the end of its stderr when it did not exit cleanly."""
    run = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                         timeout=timeout_s, cwd=ROOT)
    assert run.returncode == 0, f"the child exited with {run.returncode}: {run.stderr[-600:]}"
    return json.loads(run.stdout)
