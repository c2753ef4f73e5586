"""The objects alive before the first ``Slam`` moved out of the cyclic garbage collector's way.

CPython's cyclic collector walks every tracked object on a full collection, and after importing
numba, gtsam and numpy a process holds a great many of them, nearly all modules,
classes and functions that live as long as the process. A full collection runs in whichever
thread allocates at that moment and holds the interpreter lock throughout, so it stalls local
SLAM even when global SLAM's worker set it off, and on long logs it can be the slowest
``Slam.add_scan`` of a run. ``freeze_startup_objects`` moves the objects alive at the first
``Slam`` to the collector's permanent generation (``gc.freeze``, as servers do before forking),
so later collections walk only what was made since.

Frozen objects are still freed when their last reference goes; only a reference cycle among
them that becomes garbage later is never freed. ``Slam.__new__`` calls this before the Slam
exists, so no Slam, and no cycle through one, is ever frozen. Once per process.
"""
from __future__ import annotations

import gc

_frozen = False


def freeze_startup_objects() -> int:
    """``gc.collect`` (cycles that are garbage now are freed, not frozen), then ``gc.freeze``, the
    first time only; returns how many objects the permanent generation holds."""
    global _frozen
    if not _frozen:
        _frozen = True
        gc.collect()
        gc.freeze()
    return gc.get_freeze_count()


__all__ = ["freeze_startup_objects"]
