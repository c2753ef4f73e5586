"""Resident memory that follows the memory in use (glibc's malloc; elsewhere these do nothing).

glibc serves a request of ``M_MMAP_THRESHOLD`` bytes or more from a mapping of its own, which goes
back to the system when the block is freed. By default the threshold adapts: each time such a
block is freed it rises to that block's size (up to 32 MB), so after the first submap grid or
precomputation stack is freed, the next ones of that size come from the heap, and a long run
leaves the heap full of freed holes that stay resident (mallopt(3), "M_MMAP_THRESHOLD"). Setting
the threshold turns the adaptation off; ``malloc_trim`` hands back what is free inside the heap.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools

#: blocks of at least this many bytes get their own mapping (glibc's initial threshold is 128 KiB)
LARGE_BLOCK = 256 * 1024
_M_MMAP_THRESHOLD = -3  # <malloc.h>


@functools.lru_cache(maxsize=1)
def _glibc():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


def map_large_blocks(threshold: int = LARGE_BLOCK) -> bool:
    """Fix glibc's mmap threshold at ``threshold`` bytes for this process (True when set)."""
    libc = _glibc()
    return bool(libc is not None and libc.mallopt(_M_MMAP_THRESHOLD, int(threshold)))


def return_freed_memory() -> None:
    """Give memory freed inside the heap back to the system (glibc's ``malloc_trim``)."""
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)


def process_peak_mb(pid: int | str = "self") -> float | None:
    """The high-water mark of a process's own address space (VmHWM) [MB]; None where /proc does not
    say (another system, or the process has gone)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, IndexError, ValueError):
        pass
    return None


def peak_rss_mb() -> float:
    """This process's peak resident memory [MB] since its program began: VmHWM, the high-water mark
    of its own address space. The rusage figure (``ru_maxrss``) also holds, on Linux, the peak of the
    address space the exec replaced: a process forked, or vforked, from a larger one (a benchmark,
    a test runner) reports at least that one's peak. rusage where /proc is not there."""
    own = process_peak_mb()
    if own is not None:
        return own
    import resource
    import sys

    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024 if sys.platform != "darwin" else kb / 1024 / 1024
