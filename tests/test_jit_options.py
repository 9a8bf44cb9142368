"""Kernels compiled for the CPU they run on, with a cache key that names that CPU."""

from pathlib import Path

import pytest

from diffsolids.solvers.forms import compile_args, cpu_fingerprint

CPUINFO = """processor\t: 0
vendor_id\t: GenuineIntel
cpu family\t: 6
model\t\t: 85
model name\t: Some Xeon
flags\t\t: fpu sse2 avx avx2 avx512f

processor\t: 1
vendor_id\t: GenuineIntel
"""


def test_fingerprint_names_model_and_instruction_sets(tmp_path):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    a.write_text(CPUINFO)
    b.write_text(CPUINFO.replace(" avx512f", ""))  # same model, fewer instruction sets
    c.write_text(CPUINFO.replace("processor\t: 1", "processor\t: 1\nflags\t\t: other"))
    assert cpu_fingerprint(a) != cpu_fingerprint(b)
    assert cpu_fingerprint(a) == cpu_fingerprint(c)  # only the first processor counts
    assert cpu_fingerprint(tmp_path / "missing") is None


def test_native_flags_carry_the_fingerprint(monkeypatch):
    monkeypatch.delenv("DIFFSOLIDS_JIT_CFLAGS", raising=False)
    args = compile_args()
    cpu = cpu_fingerprint()
    if cpu is None:
        assert "-march=native" not in args  # portable flags where the CPU is unknown
    else:
        assert "-march=native" in args and f"-DDIFFSOLIDS_CPU_{cpu}" in args
    monkeypatch.setenv("DIFFSOLIDS_JIT_CFLAGS", "-O1 -g0")
    assert compile_args() == ["-O1", "-g0"]


@pytest.mark.skipif(not Path("/proc/cpuinfo").exists(), reason="needs /proc/cpuinfo")
def test_this_machine_has_a_fingerprint():
    assert cpu_fingerprint() is not None
