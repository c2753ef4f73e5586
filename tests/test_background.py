"""Global SLAM on a worker thread with its solver in a child process (``loop_closure.background``)."""
import json
import subprocess
import sys

import pytest

import slam2d
from conftest import BUNDLED
from slam2d.backend.background import Background
from slam2d.config import config_from_dict


def _records(path):  # every field but the search's wall time
    return [{k: v for k, v in json.loads(line).items() if k != "search_ms"} for line in path.read_text().splitlines()]


def test_background_gives_the_outputs_of_the_caller_thread(tmp_path):
    """Same trajectory, map and constraints, byte for byte, as global SLAM on the caller's thread with
    gtsam in-process: how far behind the worker runs changes nothing."""
    outs = {}
    for background in (True, False):
        slam = slam2d.Slam(config_from_dict({"loop_closure": {"background": background}}))
        for scan in slam2d.open_source(BUNDLED):
            slam.add_scan(scan)
        outs[background] = slam.finish().save(tmp_path / str(background))
    for name in ("trajectory.txt", "map.pgm", "map.yaml"):
        assert (outs[True] / name).read_bytes() == (outs[False] / name).read_bytes(), name
    a, b = _records(outs[True] / "constraints.jsonl"), _records(outs[False] / "constraints.jsonl")
    assert a == b and sum(r["in_final_graph"] for r in a) >= 5
    s = json.loads((outs[True] / "summary.json").read_text())["loop_closure"]
    assert s["solver_process_peak_rss_mb"] > 0 and s["optimizations"] >= 2
    for background in (True, False):
        t = json.loads((outs[background] / "summary.json").read_text())["timings"]
        # the caller's CPU time in add_scan: some, and never more than its wall time
        assert 0 < t["add_scan"]["cpu_s"] <= t["add_scan"]["total_s"] + 1e-3
        assert ("global_worker_cpu_s" in t) == background
    assert json.loads((outs[True] / "summary.json").read_text())["timings"]["global_worker_cpu_s"] > 0


def test_the_worker_cpu_time_counts_its_calls_work_not_its_waits():
    import time

    b = Background()

    def spin(seconds):
        end = time.thread_time() + seconds
        while time.thread_time() < end:
            pass

    b.submit(spin, 0.2)
    b.submit(time.sleep, 0.3)  # waiting burns no CPU
    b.wait()
    spin(0.2)  # nor does the caller's own work count
    b.join()
    assert 0.19 <= b.cpu_s < 0.3


def test_the_caller_process_does_not_load_gtsam():
    code = ("import sys, slam2d\n"
            f"slam = slam2d.Slam()\n"
            f"for _, s in zip(range(300), slam2d.open_source({str(BUNDLED)!r})): slam.add_scan(s)\n"
            "r = slam.finish()\n"
            "assert r.summary['loop_closure']['optimizations'] >= 1\n"
            "print('gtsam' in sys.modules)\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "False"


def test_a_global_slam_failure_reaches_the_caller(monkeypatch):
    """An exception on the worker is raised on the caller's thread (by a later add_scan, sync or finish),
    and again on every later call: the work after it was skipped."""
    from slam2d.backend.global_slam import GlobalSlam

    calls = []

    def broken(self, scan, *args):
        calls.append(scan.index)
        if len(calls) == 20:
            raise ValueError("injected failure")

    monkeypatch.setattr(GlobalSlam, "add_node", broken)
    slam = slam2d.Slam()
    with pytest.raises(ValueError, match="injected failure"):
        for _, scan in zip(range(400), slam2d.open_source(BUNDLED)):
            slam.add_scan(scan)
        slam.sync()
    with pytest.raises(ValueError, match="injected failure"):
        slam.sync()
    assert len(calls) == 20  # nothing after the failure ran


def test_sync_waits_for_the_queue():
    b = Background()
    seen = []
    for i in range(200):
        b.submit(lambda i=i: (seen.append(i), sum(range(2000))))
    b.wait()
    assert seen == list(range(200))  # all of them, in order
    b.join()


def test_the_worker_uses_every_numba_thread_only_while_the_caller_waits():
    """While the caller works, the worker's kernels run on one numba thread (local SLAM has the
    other core); calls that run while the caller waits in ``wait`` or ``join`` get them all."""
    import threading

    import numba

    if numba.get_num_threads() < 2:
        pytest.skip("numba has one thread here")
    b = Background()
    seen = []

    def record():
        seen.append(numba.get_num_threads())

    b.submit(record)
    for _ in range(500):  # the caller keeps working (it does not wait) until the call has run
        if seen:
            break
        threading.Event().wait(0.01)
    for finish in (b.wait, b.join):
        gate = threading.Event()
        b.submit(gate.wait)  # the next call starts only once the caller is waiting
        b.submit(record)
        threading.Timer(0.3, gate.set).start()
        finish()
    assert seen == [1, numba.get_num_threads(), numba.get_num_threads()]


def test_a_long_worker_call_takes_every_core_for_its_searches_once_the_caller_waits():
    """A call that began while the caller worked (one numba thread) asks again before each of global
    SLAM's searches: those that run after the caller started waiting get every thread."""
    import threading

    import numba

    if numba.get_num_threads() < 2:
        pytest.skip("numba has one thread here")
    slam = slam2d.Slam(config_from_dict({"loop_closure": {"background": True}}))
    b, cores = slam._background, slam.global_slam.cores
    seen, started = [], threading.Event()

    def long_call():
        with cores.share():  # a search while the caller still works
            seen.append(numba.get_num_threads())
        started.set()
        for _ in range(1000):  # the call goes on until the caller waits for it
            if b.caller_waits():
                break
            threading.Event().wait(0.01)
        with cores.share():  # a search after the caller started waiting
            seen.append(numba.get_num_threads())
        seen.append(numba.get_num_threads())  # outside a search: the count the call started with

    b.submit(long_call)
    assert started.wait(10)
    b.wait()
    assert seen == [1, numba.get_num_threads(), 1]
    b.join()


def test_caller_cores_leave_one_thread_only_while_the_worker_is_busy():
    """Local SLAM's parallel kernels ask right before they run: one numba thread while global SLAM's
    worker is busy, all of them otherwise, and the count is restored afterwards (also on an error)."""
    import numba

    from slam2d.threads import CallerCores

    n = numba.get_num_threads()
    busy = [True]
    cores = CallerCores(lambda: busy[0])
    with cores.share():
        assert numba.get_num_threads() == 1
    assert numba.get_num_threads() == n
    busy[0] = False
    with cores.share():
        assert numba.get_num_threads() == n
    busy[0] = True
    with pytest.raises(RuntimeError):
        with cores.share():
            raise RuntimeError("kernel failed")
    assert numba.get_num_threads() == n
    with CallerCores().share():  # nobody else: all threads
        assert numba.get_num_threads() == n


def test_the_switch_interval_is_short_while_a_worker_lives_and_restored_after():
    """While any worker runs, a thread waiting for the interpreter lock gets it within
    ``SWITCH_INTERVAL``; the value before the first worker comes back when the last one ends.
    (In a fresh interpreter: workers of this session's dropped Slams may still be alive here.)"""
    code = """if True:
        import sys
        from slam2d.backend.background import SWITCH_INTERVAL, Background
        sys.setswitchinterval(0.004)
        a, b = Background(), Background()
        seen = []
        a.submit(lambda: seen.append(sys.getswitchinterval()))
        a.wait()
        a.join()
        after_one = sys.getswitchinterval()
        b.join()
        print(SWITCH_INTERVAL, seen[0], after_one, sys.getswitchinterval())
    """
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    limit, during, after_one, after_both = map(float, out.stdout.split())
    assert during == pytest.approx(min(0.004, limit))
    assert after_one == pytest.approx(min(0.004, limit))  # b still runs
    assert after_both == pytest.approx(0.004)


def test_importing_slam2d_asks_for_passive_openmp_threads_unless_the_user_chose():
    """numba's OpenMP workers would spin on the core global SLAM's worker needs."""
    import os

    code = "import os, slam2d; print(os.environ.get('OMP_WAIT_POLICY'))"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "PASSIVE"
    env["OMP_WAIT_POLICY"] = "ACTIVE"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "ACTIVE"
