"""Tests of bench/: each runs its benchmark for real in a fresh process (small budgets, no
timing limits) and checks the JSON shape its docstring names."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def run_json(script: str, *args: str, timeout: float = 300) -> dict:
    """``bench/<script> *args --json`` in a fresh interpreter: its one line of JSON (progress
    goes to stderr); fails the test on a non-zero exit, showing stderr."""
    result = subprocess.run([sys.executable, str(ROOT / "bench" / script), *args, "--json"], cwd=ROOT,
                            capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, result.stderr[-3000:]
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1, lines
    return json.loads(lines[0])
