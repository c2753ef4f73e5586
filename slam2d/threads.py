"""Work split over threads for numba kernels that release the interpreter lock (``nogil``).

For the stages that run when nothing else does (after the last optimization): each item is
computed on its own, so how the items are split changes no result.
"""
from __future__ import annotations

from contextlib import contextmanager

import numpy as np


def in_threads(fn, n: int) -> None:
    """``fn(lo, hi)`` over [0, n) split into one contiguous share per numba thread, run on that many
    Python threads (the kernels release the interpreter lock)."""
    import numba

    k = max(1, min(numba.get_num_threads(), n // 256))
    if k == 1:
        fn(0, n)
        return
    from concurrent.futures import ThreadPoolExecutor

    bounds = np.linspace(0, n, k + 1).astype(int)
    with ThreadPoolExecutor(k) as pool:
        for f in [pool.submit(fn, int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]:
            f.result()


class CallerCores:
    """The numba threads a thread's parallel kernels may use at this moment: one while ``busy()`` says
    another thread of the process is working (it has the second core then, and a parallel kernel
    would wait at its barrier for a thread the OS has descheduled), otherwise ``most`` (None: the
    thread's own count). Asked right before each such kernel, not once per scan or per queued call:
    local SLAM's caller shares with global SLAM's worker, which often finishes a node while the
    next scan is matched, and the worker's long calls (a wide loop search) share with the caller
    until it stops to wait for them. Kernels give the same results on any number of threads, so
    this changes timings only."""

    def __init__(self, busy=None, most: int | None = None):
        self.busy = busy
        self.most = most

    @contextmanager
    def share(self):
        if self.busy is None:
            yield
            return
        import numba

        n = numba.get_num_threads()
        want = 1 if self.busy() else (self.most or n)
        if want == n:
            yield
            return
        numba.set_num_threads(want)
        try:
            yield
        finally:
            numba.set_num_threads(n)


__all__ = ["CallerCores", "in_threads"]
