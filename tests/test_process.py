"""Process-wide settings: freed memory is reused instead of being faulted in afresh."""

import subprocess
import sys

import pytest

PROBE = """
import resource, sys
import numpy as np
if sys.argv[1] == "reuse":
    from pipeline.process import reuse_freed_memory
    assert reuse_freed_memory()
sizes = [(1 << 20) * k for k in (3, 5, 2, 7, 4)]
def allocate():
    for n in sizes:
        a, b = np.ones(n // 8), np.ones(n // 16)
        del a
        c = np.ones(n // 4)
        del b, c
allocate()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    allocate()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _page_faults(mode: str) -> int:
    result = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    return int(result.stdout)


def test_arrays_of_a_few_megabytes_freed_and_allocated_again_fault_no_pages_in():
    from pipeline.process import reuse_freed_memory

    if not reuse_freed_memory():
        pytest.skip("this C library has no mallopt (not glibc)")
    plain = _page_faults("plain")
    if plain < 100:
        pytest.skip(f"this C library reuses freed memory by itself ({plain} page faults in the probe)")
    assert _page_faults("reuse") < plain / 10
