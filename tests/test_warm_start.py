"""What the first Slam of a process readies before its first scan: ``slam2d.gc_freeze`` (the start-up
objects out of the collector's way, no Slam ever among them) and ``slam2d.kernel_cache`` (the
kernels earlier runs loaded, loaded ahead; not those only other callers used).

Each check runs in fresh interpreters: it asserts the state of a process before and after its
first ``Slam``, which this test process has long passed.
"""
import os
import subprocess
import sys

from conftest import BUNDLED

_FREEZE = """
import gc, weakref
import slam2d
assert gc.get_freeze_count() == 0
first = slam2d.Slam()
frozen = gc.get_freeze_count()
assert frozen > 10000, frozen          # numba, gtsam, numpy: far more than a handful
second = slam2d.Slam()
assert gc.get_freeze_count() == frozen  # once per process
first.cycle, second.cycle = first, second  # as an observer that keeps its Slam would make
refs = [weakref.ref(first), weakref.ref(second)]
del first, second
gc.collect()
assert all(r() is None for r in refs), "a Slam was frozen, or is held by what was"
print("ok")
"""


# a run on the bundled dataset, after a direct call of score_window with a float64 grid: the
# pipeline's own calls use float32 grids (real-time matcher), and only those are remembered
_RUN = """
import sys
import numpy as np
from slam2d.matching import _kernels as K
K.score_window(np.zeros((4, 4), np.float64), np.zeros((1, 2, 2), np.int32), 0, np.float64(0.0), 1.0)
import slam2d
slam2d.Slam().run(slam2d.open_source(sys.argv[1]))
print("ok")
"""

_AHEAD = """
from numba import types
import slam2d
from slam2d.matching import _kernels as K
sig = lambda t: (types.Array(t, 2, "C"), types.Array(types.int32, 3, "C"), types.int64, t, types.float64)
assert not K.score_window.overloads
slam2d.Slam()
assert sig(types.float32) in K.score_window.overloads, "what the run used was not loaded ahead"
assert sig(types.float64) not in K.score_window.overloads, "a direct call's signature was loaded too"
print("ok")
"""


def _run(code, *args):
    p = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and p.stdout.strip().endswith("ok"), p.stdout + p.stderr


def test_the_kernels_an_earlier_run_loaded_are_loaded_before_the_first_scan():
    from slam2d import kernel_cache
    from slam2d.matching import _kernels as K

    record = kernel_cache._record_path(K.score_window)  # forgotten: the run below must remember it
    if os.path.exists(record):
        os.remove(record)
    _run(_RUN, BUNDLED)
    assert os.path.exists(record)
    _run(_AHEAD)


def test_the_first_slam_freezes_the_start_up_objects_but_no_slam_is_ever_frozen():
    _run(_FREEZE)
