"""Global SLAM beside local SLAM (Hess et al. 2016, Sec. V; Cartographer's background work queue).

``add_scan`` hands each new node and finished submap to one worker thread, which feeds them to
``GlobalSlam`` in the order they came, and returns without waiting: loop search and pose-graph
bookkeeping run beside the next scans. Their kernels release the interpreter lock (numba
``nogil``), and the pose graph is solved in a child process (``solver_process.py``), since a
GTSAM solve would hold it throughout. One thread, fed in input order, and local SLAM that never
reads global SLAM's results: what global SLAM computes does not depend on how far behind it runs,
so outputs are the same as when everything runs on the caller's thread (tested). Only the
estimate ``add_scan`` returns depends on timing: it carries the latest optimization's correction.
An exception on the worker is raised on the caller's next call.

The worker's parallel kernels run on one numba thread while the caller works (local SLAM has the
other core), and on all of them while the caller waits for the worker (``wait``, ``join``): the
loop search left at the end of a run then uses both cores. A call is given its count when it
starts, and global SLAM's searches ask again right before they run (``GlobalSlam.cores``), so a
long call that began while the caller worked (a finished submap's wide search near the end of a
log) takes the second core as soon as the caller waits. Kernels give the same results on any
number of threads.
"""
from __future__ import annotations

import queue
import sys
import threading
import time
import weakref

#: the interpreter's thread switch interval [s] while a worker runs (``_SwitchInterval``)
SWITCH_INTERVAL = 0.001


class _SwitchInterval:
    """While any worker lives, the interpreter hands its lock to a waiting thread after at most
    ``SWITCH_INTERVAL`` instead of CPython's 5 ms: local SLAM re-takes the lock after every numba
    kernel, and would otherwise often wait most of 5 ms while the worker runs Python between its
    kernels. The value before the first worker is restored when the last one ends."""

    _lock = threading.Lock()
    _users = 0
    _saved = None

    @classmethod
    def enter(cls):
        with cls._lock:
            if cls._users == 0:
                cls._saved = sys.getswitchinterval()
                sys.setswitchinterval(min(cls._saved, SWITCH_INTERVAL))
            cls._users += 1

    @classmethod
    def leave(cls):
        with cls._lock:
            cls._users -= 1
            if cls._users == 0 and cls._saved is not None:
                sys.setswitchinterval(cls._saved)


class Background:
    """Calls made in order on one daemon thread."""

    def __init__(self, name: str = "slam2d-global"):
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._error: BaseException | None = None
        self._idle = threading.Event()  # set while the worker waits for work
        self._waited = threading.Event()  # set while the caller waits for the worker: its cores are free
        self._cpu = [0.0]  # the worker's CPU time in the calls it ran [s] (``cpu_s``)
        self._thread = threading.Thread(target=_work, args=(self._queue, self, self._idle, self._waited, self._cpu),
                                        name=name, daemon=True)
        # counted here, not when the thread gets going: a worker that has not started yet still lives
        # for ``_SwitchInterval`` (another's end must not restore the interval before it runs)
        _SwitchInterval.enter()
        try:
            self._thread.start()
        except BaseException:
            _SwitchInterval.leave()
            raise
        # a Slam dropped without finish: the thread ends once it has drained its queue
        self._finalizer = weakref.finalize(self, self._queue.put, None)

    def submit(self, fn, *args) -> None:
        """Queue ``fn(*args)``; raises what an earlier call raised."""
        self.raise_error()
        self._queue.put((fn, args))

    @property
    def cpu_s(self) -> float:
        """The worker thread's CPU time in the calls it has run [s] (``time.thread_time``): beside the
        caller's own (``Slam``'s ``add_scan`` timing), what global SLAM costs the cores."""
        return self._cpu[0]

    def caller_waits(self) -> bool:
        """The caller is waiting for the worker (``wait``, ``join``): its cores are free."""
        return self._waited.is_set()

    def idle(self) -> bool:
        """Nothing queued and nothing running (a hint: the worker may take up work as this returns)."""
        return self._idle.is_set() and self._queue.empty()

    def wait(self) -> None:
        """Wait until every call queued so far has run; raise what one of them raised."""
        done = threading.Event()
        self.submit(done.set)
        self._waited.set()
        try:
            while not done.wait(0.1):  # the thread may end on an error before it reaches the marker
                if not self._thread.is_alive() or self._error is not None:
                    break
        finally:
            self._waited.clear()
        self.raise_error()

    def join(self) -> None:
        """Wait until every queued call has run; raise what one of them raised."""
        if self._finalizer.alive:
            self._waited.set()
            self._finalizer()
            self._thread.join()
        self.raise_error()

    def raise_error(self) -> None:
        """Raise what a call raised (again on every later call: the work after it was skipped)."""
        if self._error is not None:
            raise self._error


def _work(q: queue.SimpleQueue, owner: Background, idle: threading.Event, waited: threading.Event, cpu: list):
    import numba

    # holds the Background only while reporting an error, so dropping it ends the thread
    ref = weakref.ref(owner)
    del owner
    threads = numba.get_num_threads()  # numba's thread count is per calling thread
    try:  # entered by ``Background.__init__``
        _drain(q, ref, idle, waited, threads, cpu)
    finally:
        _SwitchInterval.leave()


def _drain(q, ref, idle, waited, threads, cpu):
    import numba

    failed = False
    while True:
        if q.empty():
            idle.set()
        item = q.get()
        idle.clear()
        if item is None:
            return
        if failed:  # after a failure the rest is skipped: its input is incomplete
            continue
        fn, args = item
        try:
            numba.set_num_threads(threads if waited.is_set() else 1)
            c0 = time.thread_time()
            fn(*args)
            cpu[0] += time.thread_time() - c0
        except BaseException as e:  # noqa: BLE001 - handed to the caller's thread
            failed = True
            b = ref()
            if b is not None:
                b._error = e
