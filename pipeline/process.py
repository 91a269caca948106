"""Process-wide settings shared by the commands and the benchmarks."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
LARGEST_HEAP_BLOCK = 32 << 20
"""Bytes: blocks up to this size come from the heap, not from a fresh mmap (glibc's ceiling on 64-bit)."""
KEPT_FREE_BYTES = 256 << 20
"""Freed heap memory kept for reuse before any is returned to the kernel."""
HEAP_GROWTH_BYTES = 16 << 20
"""Extra room asked of the kernel whenever the heap grows, so that it grows in few steps."""


@functools.cache
def _libc_function(name: str):
    """A function of the C library (None where it has none): looked up once, since finding the library
    runs ``ldconfig`` and the runner trims after every unit."""
    try:
        return getattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), name)
    except (OSError, AttributeError):
        return None


def reuse_freed_memory() -> bool:
    """Make glibc's malloc keep freed memory for the next allocation instead of handing it back.

    A forward pass allocates and frees feature tensors of a few MB each, and by default glibc maps
    each afresh and unmaps it on free, so the kernel faults in and zeroes every page again: about 4-5 k
    page faults and 6-21 ms of system time per forward pass on a val50 bed. Returns False where the C
    library has no ``mallopt`` (not glibc), which changes nothing else."""
    mallopt = _libc_function("mallopt")
    if mallopt is None:
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return all(mallopt(option, value) == 1 for option, value in (
        (_M_MMAP_THRESHOLD, LARGEST_HEAP_BLOCK), (_M_TRIM_THRESHOLD, KEPT_FREE_BYTES), (_M_TOP_PAD, HEAP_GROWTH_BYTES)))


def hand_back_freed_memory() -> bool:
    """Return the free pages of every malloc arena to the kernel (glibc's ``malloc_trim``).

    A long run's threads (capture, fusion, perception) each allocate from their own arena, and the
    memory ``reuse_freed_memory`` keeps for reuse fragments over thousands of frames: resident memory
    creeps up although nothing is held. Trimming once per fused unit keeps it flat for a page fault
    per reused page. Returns False where the C library has no ``malloc_trim`` (not glibc)."""
    trim = _libc_function("malloc_trim")
    if trim is None:
        return False
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    trim(0)
    return True


def let_idle_threads_sleep() -> None:
    """Make OpenMP's idle threads sleep rather than spin (``OMP_WAIT_POLICY=PASSIVE``), unless the user
    set a policy. Takes effect only before torch and Open3D load.

    When stages run side by side on few cores (fusion's Open3D calls in one process, perception's
    torch in another), a thread spinning after its parallel region burns the core the other stage
    needs: on 2 cores, a live turn's last frame to its detections took 1.40 s spinning and 0.75 s
    sleeping (bench/pipeline.py's chain, one run each)."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
