"""Where a result came from: git commit, package versions, torch threads, host (one helper).

Every training run writes it to ``run.json`` when it starts and into ``result.json`` when it
ends; the demo's ``metrics.json`` carries it too. A commit is recorded when the code runs from a
git checkout (``dirty``: uncommitted changes to tracked files), else None.
"""

from __future__ import annotations

import importlib.metadata
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

PACKAGES = ("formation-stack", "torch", "numpy", "scipy", "python-fcl", "qpsolvers", "osqp", "filterpy",
            "eclipse-zenoh", "pymunk", "onnx", "onnxruntime", "onnxscript")
_REPO = Path(__file__).resolve().parents[1]


def git_commit(root: Path = _REPO) -> dict[str, Any] | None:
    """``{"commit", "dirty"}`` of the checkout at ``root``, None outside one (or without git)."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
    try:
        commit = git("rev-parse", "HEAD")
        dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError):
        return None
    return {"commit": commit, "dirty": dirty}


def package_versions(names: tuple[str, ...] = PACKAGES) -> dict[str, str | None]:
    versions: dict[str, str | None] = {}
    for name in names:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def provenance() -> dict[str, Any]:
    """The record: git, package versions, Python, torch threads, host, CPUs, command line, time."""
    import torch

    return {"git": git_commit(), "packages": package_versions(), "python": platform.python_version(),
            "torch_threads": torch.get_num_threads(), "host": platform.node(),
            "machine": platform.machine(), "cpus": os.cpu_count(), "argv": list(sys.argv),
            "time_unix": time.time()}


__all__ = ["git_commit", "package_versions", "provenance"]
