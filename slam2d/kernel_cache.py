"""The numba kernels a run will need, loaded from numba's on-disk cache before the first scan.

numba compiles a kernel, or loads it from its cache (``cache=True``), on the first call with each
type signature. A load takes milliseconds to tens of milliseconds with the interpreter lock held,
and first calls come inside ``Slam.add_scan``: the first scans, the first submap that becomes the
matched one, global SLAM's first loop search (whose loads block local SLAM's thread too). A
real-time system loads before the data comes.

Which signatures to load: not every one the cache holds. It also holds the signatures of
kernels only other kernels call (compiled into their callers' code) and of calls the tests make
with other types, and each loaded signature costs the process the memory of its code. So
``Slam.finish`` remembers, beside the kernel's cache index, the cached signatures its run loaded
(``remember``), and the next process's first ``Slam`` loads those (``load_remembered``): on a
machine where slam2d ran before, what a run needs is loaded before its first scan.

numba has no public call for "what does the cache hold", so the index is read through the
dispatcher's ``_cache`` attribute (as numba 0.68 lays it out). Where anything fails nothing is
loaded ahead and kernels load on first use: results never depend on this, only when loads happen.
"""
from __future__ import annotations

import importlib
import json
import logging
import os

log = logging.getLogger(__name__)

#: the modules holding slam2d's numba kernels
KERNEL_MODULES = ("slam2d._kernels", "slam2d.grid._kernels", "slam2d.matching._kernels", "slam2d.backend._kernels")

_loaded = False


def kernels() -> list:
    """Every numba dispatcher of ``KERNEL_MODULES``."""
    from numba.core.registry import CPUDispatcher

    return [fn for name in KERNEL_MODULES for fn in vars(importlib.import_module(name)).values()
            if isinstance(fn, CPUDispatcher)]


def cached_signatures(dispatcher) -> list:
    """The type signatures ``dispatcher``'s on-disk cache holds for its current code on this
    machine (empty without a cache, or when it belongs to other code or another numba)."""
    cache = getattr(dispatcher, "_cache", None)
    index = getattr(getattr(cache, "_cache_file", None), "_load_index", None)
    if index is None or not getattr(cache, "_enabled", False):
        return []
    codegen = dispatcher.targetctx.codegen()
    return [key[0] for key in index() if key == cache._index_key(key[0], codegen)]


def _record_path(dispatcher) -> str:
    return dispatcher._cache._cache_file._index_path + ".slam2d-used"


def _remembered(dispatcher) -> set[str]:
    try:
        with open(_record_path(dispatcher)) as f:
            return set(json.load(f))
    except (OSError, ValueError, AttributeError):
        return set()


def loaded() -> dict:
    """Per kernel, the signatures loaded in this process now (to tell ``remember`` what came since)."""
    return {fn: {str(s) for s in fn.overloads} for fn in kernels()}


def remember(before: dict) -> None:
    """Add the cached signatures loaded since ``before`` (``loaded()``) to each kernel's record."""
    for fn in kernels():
        try:
            new = {str(s) for s in fn.overloads} - before.get(fn, set())
            if not new:
                continue
            cached = {str(tuple(s)) for s in cached_signatures(fn)}
            old = _remembered(fn)
            keep = old | (new & cached)
            if keep == old:
                continue
            path = _record_path(fn)
            tmp = f"{path}.{os.getpid()}.tmp"
            with open(tmp, "w") as f:
                json.dump(sorted(keep), f)
            os.replace(tmp, path)
        except Exception as e:  # noqa: BLE001 - a read-only cache, changed numba internals: load on first use
            log.debug("kernel cache: not remembered for %s (%s)", getattr(fn, "__name__", "?"), e)


def load_remembered() -> int:
    """Load every remembered signature the cache holds, once per process; returns how many."""
    global _loaded
    if _loaded:
        return 0
    _loaded = True
    n = 0
    for fn in kernels():
        try:
            want = _remembered(fn)
            for sig in cached_signatures(fn):
                if str(tuple(sig)) in want and tuple(sig) not in fn.overloads:
                    fn.compile(tuple(sig))
                    n += 1
        except Exception as e:  # noqa: BLE001 - as in ``remember``
            log.debug("kernel cache: %s not loaded ahead (%s)", getattr(fn, "__name__", "?"), e)
    return n


__all__ = ["KERNEL_MODULES", "kernels", "cached_signatures", "loaded", "remember", "load_remembered"]
