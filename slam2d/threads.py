"""Work split over threads for numba kernels that release the interpreter lock (``nogil``).

For the stages that run when nothing else does (after the last optimization): each item is
computed on its own, so how the items are split changes no result.
"""
from __future__ import annotations

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


__all__ = ["in_threads"]
