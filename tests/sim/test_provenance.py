"""sim.provenance: the CPU a result came from, read from /proc/cpuinfo's first processor."""

from __future__ import annotations

import torch

from sim.provenance import cpu_model, provenance

CPUINFO = """processor\t: 0
vendor_id\t: GenuineIntel
cpu family\t: 6
model\t\t: 143
model name\t: Intel(R) Xeon(R) Platinum 8480C
stepping\t: 8
flags\t\t: fpu avx2 avx512f

processor\t: 1
cpu family\t: 25
model\t\t: 1
model name\t: AMD EPYC 7763 64-Core Processor
stepping\t: 1
"""


def test_cpu_model_reads_the_first_processor(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text(CPUINFO)
    assert cpu_model(info) == {"model_name": "Intel(R) Xeon(R) Platinum 8480C", "family": 6, "model": 143,
                               "stepping": 8}


def test_cpu_model_without_cpuinfo_names_what_platform_knows(tmp_path):
    out = cpu_model(tmp_path / "missing")
    assert (out["family"], out["model"], out["stepping"]) == (None, None, None)


def test_provenance_records_the_instruction_set_torch_runs_on():
    assert provenance()["cpu"]["capability"] == torch.backends.cpu.get_cpu_capability()


def test_provenance_records_the_variables_that_choose_the_kernels(monkeypatch):
    """A run held to other kernels (here MKL's AVX2 code path) trains differently: the record says so."""
    monkeypatch.setenv("MKL_ENABLE_INSTRUCTIONS", "AVX2")
    monkeypatch.delenv("ATEN_CPU_CAPABILITY", raising=False)
    assert provenance()["cpu"]["kernel_env"]["MKL_ENABLE_INSTRUCTIONS"] == "AVX2"
    assert "ATEN_CPU_CAPABILITY" not in provenance()["cpu"]["kernel_env"]
