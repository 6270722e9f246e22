"""Where a result came from: git commit, package versions, torch threads, host, CPU (one helper).

Every training run writes it to ``run.json`` when it starts and into ``result.json`` when it
ends; the demo's ``metrics.json`` carries it too. A commit is recorded when the code runs from a
git checkout (``dirty``: uncommitted changes to tracked files), else None. The CPU is recorded
because the same command runs 2-3x faster or slower on the processors this project's machines
change between, and torch picks its kernels by instruction set (``capability``: AVX2, AVX512,
...): a timing, or a run that does not repeat, can be read against the processor it ran on.
The variables that override those choices (:data:`KERNEL_ENV`) are recorded when set: seed 3 of
the 3-5 generalist converges at 2304 episodes on this project's AVX-512 machine, at 2736 with
MKL held to AVX2, at 1248 with MKL held to AVX, at 1728 with MKL and ATen held to AVX2, and not
within 3200 with ATen alone held to AVX2 (2026-12-05): a run repeats to the bit only on the
same kernels.
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
KERNEL_ENV = ("ATEN_CPU_CAPABILITY", "MKL_ENABLE_INSTRUCTIONS", "MKL_CBWR", "ONEDNN_MAX_CPU_ISA",
              "DNNL_MAX_CPU_ISA", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""Environment variables that change which kernels torch, MKL and oneDNN run (or on how many threads)."""


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


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> dict[str, Any]:
    """``{"model_name", "family", "model", "stepping"}`` of the first processor in ``cpuinfo``
    (Linux); ``model_name`` from :func:`platform.processor` and None for the rest elsewhere."""
    fields = {"model name": "model_name", "cpu family": "family", "model": "model", "stepping": "stepping"}
    out: dict[str, Any] = dict.fromkeys(fields.values())
    try:
        text = cpuinfo.read_text()
    except OSError:
        return {**out, "model_name": platform.processor() or None}
    for line in text.split("\n\n", 1)[0].splitlines():
        key, _, value = (part.strip() for part in line.partition(":"))
        if key in fields:
            out[fields[key]] = value if key == "model name" else int(value) if value.isdigit() else value
    return out


def provenance() -> dict[str, Any]:
    """The record: git, package versions, Python, torch threads, host, CPUs (count, model, the
    instruction set torch's kernels use and the :data:`KERNEL_ENV` variables set), command line, time."""
    import torch

    return {"git": git_commit(), "packages": package_versions(), "python": platform.python_version(),
            "torch_threads": torch.get_num_threads(), "host": platform.node(),
            "machine": platform.machine(), "cpus": os.cpu_count(),
            "cpu": {**cpu_model(), "capability": torch.backends.cpu.get_cpu_capability(),
                    "kernel_env": {k: os.environ[k] for k in KERNEL_ENV if k in os.environ}},
            "argv": list(sys.argv), "time_unix": time.time()}


__all__ = ["KERNEL_ENV", "cpu_model", "git_commit", "package_versions", "provenance"]
