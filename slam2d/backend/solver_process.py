"""The pose graph solved in a child process (Cartographer runs its optimization on a background
thread pool; in CPython a thread is not enough).

GTSAM's Python binding holds the interpreter lock for the whole of a solve, so a solve on any
thread of the caller's process stops every other thread of it, the caller's included, for as
long as it takes. ``RemotePoseGraph`` has ``PoseGraph``'s interface but keeps only a mirror: the
node estimates and the loop constraints with their records. Factors are queued and sent in a
batch before each solve to a child process that holds the real ``PoseGraph`` (``python -m
slam2d.backend.solver_process``: numpy and gtsam only), which solves, runs the residual check
and sends back every node's estimate and the loops it dropped. The child sees the same factors
in the same order as an in-process graph would, so the estimates are the same numbers (tested).
The caller's process then never imports gtsam.
"""
from __future__ import annotations

import math
import os
import subprocess
import sys
import weakref
from multiprocessing.connection import Connection

import numpy as np

from slam2d.allocator import peak_rss_mb
from slam2d.types import LoopFactor


def _stored(p) -> tuple[float, float, float]:
    """A pose as gtsam's ``Pose2`` gives it back: the heading goes through (cos, sin) and atan2."""
    x, y, t = (float(v) for v in p)
    return x, y, math.atan2(math.sin(t), math.cos(t))


class SolverError(RuntimeError):
    """The solver process failed (its message says how) or went away."""


class RemotePoseGraph:
    """``PoseGraph`` (``pose_graph.py``) with its factors and solver in a child process."""

    def __init__(self, huber_scale: float = 1.0, max_residual_trans: float = 0.3, max_residual_rot: float = 0.05,
                 incremental: bool = False):
        self._poses: dict[int, np.ndarray] = {}
        self._ops: list[tuple] = []
        self.loops: list[LoopFactor] = []
        self.removed: list[LoopFactor] = []
        self._by_id: dict[int, LoopFactor] = {}
        self._next_id = 0
        self.iterations = 0
        self.last_error = (math.nan, math.nan)
        self.peak_rss_mb = None  # the child's, once closed
        to_child_r, to_child_w = os.pipe()
        from_child_r, from_child_w = os.pipe()
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "slam2d.backend.solver_process", str(to_child_r), str(from_child_w)],
            pass_fds=(to_child_r, from_child_w), stdin=subprocess.DEVNULL, close_fds=True)
        os.close(to_child_r)
        os.close(from_child_w)
        self._send = Connection(to_child_w, readable=False)
        self._recv = Connection(from_child_r, writable=False)
        self._send.send(("init", huber_scale, max_residual_trans, max_residual_rot, incremental))
        self._finalizer = weakref.finalize(self, _shutdown, self._proc, self._send, self._recv)

    # ---- variables
    def add_node(self, j: int, pose):
        if j not in self._poses:
            self._poses[j] = np.array(_stored(pose))
            self._ops.append(("node", int(j), tuple(float(v) for v in pose)))

    def node_pose(self, j) -> np.ndarray:
        return self._poses[j].copy()

    def has_node(self, j) -> bool:
        return j in self._poses

    def all_node_poses(self) -> tuple[np.ndarray, np.ndarray]:
        ids = np.array(sorted(self._poses), dtype=np.int64)
        return ids, np.array([self._poses[j] for j in ids], dtype=float).reshape(-1, 3)

    # ---- factors
    def add_intra(self, anchor: int, j: int, relative, covariance, screened: bool = True):
        self._ops.append(("intra", int(anchor), int(j), np.asarray(relative, float), np.asarray(covariance, float),
                          bool(screened)))

    def add_loop(self, anchor: int, j: int, relative, covariance, record: dict, heading_only: bool = False) -> LoopFactor:
        f = LoopFactor(self._next_id, anchor, j, np.asarray(relative, dtype=float), record, heading_only=heading_only)
        self._next_id += 1
        self._ops.append(("loop", f.index, int(anchor), int(j), f.relative, np.asarray(covariance, float), heading_only))
        self.loops.append(f)
        self._by_id[f.index] = f
        return f

    def remove_loop(self, f: LoopFactor, reason: str):
        self._ops.append(("remove", f.index, reason))
        self._drop(f, reason)

    def _drop(self, f: LoopFactor, reason: str):
        self.loops.remove(f)
        del self._by_id[f.index]
        f.record["in_final_graph"] = False
        f.record["reason"] = reason
        self.removed.append(f)

    # ---- solve
    def _call(self, *request):
        try:
            self._send.send(("ops", self._ops))
            self._ops = []
            self._send.send(request)
            kind, payload = self._recv.recv()
        except (EOFError, OSError) as e:
            raise SolverError(f"the pose-graph solver process went away ({e})") from None
        if kind == "error":
            raise SolverError(f"pose-graph solver: {payload}")
        return payload

    def _dropped(self, dropped) -> list[LoopFactor]:
        out = []
        for lid, reason in dropped:
            f = self._by_id[lid]
            self._drop(f, reason)
            out.append(f)
        return out

    def optimize(self, max_rounds: int = 20, batch: bool = False, error: bool = True, exempt=()) -> list[LoopFactor]:
        """``PoseGraph.optimize`` in the child (``exempt``: ids of this proxy's loops); every node's
        estimate comes back."""
        r = self._call("optimize", max_rounds, batch, error, [int(i) for i in exempt])
        self._poses = {int(j): p for j, p in zip(r["ids"], r["poses"])}
        self.iterations, self.last_error = r["iterations"], r["last_error"]
        return self._dropped(r["dropped"])

    def gnc_prune(self) -> list[LoopFactor]:
        """``PoseGraph.gnc_prune`` in the child."""
        return self._dropped(self._call("gnc")["dropped"])

    def close(self):
        """Stop the child (after asking its peak memory, kept in ``peak_rss_mb``)."""
        if self._finalizer.alive:
            try:
                self.peak_rss_mb = self._call("stats")["peak_rss_mb"]
            except SolverError:
                pass
            self._finalizer()


def _shutdown(proc, send, recv):
    for c in (send, recv):
        try:
            c.close()
        except OSError:
            pass
    try:
        proc.wait(timeout=10)  # the closed pipe ends its loop
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


# ---- the child
def _serve(recv: Connection, send: Connection):
    from slam2d.backend.pose_graph import PoseGraph

    graph, loops, failed = None, {}, None
    while True:
        try:
            msg = recv.recv()
        except EOFError:
            return
        kind = msg[0]
        try:
            if kind in ("init", "ops"):  # no reply: a failure is the reply to the next request
                if failed is None:
                    graph = _apply(PoseGraph, graph, loops, msg)
                continue
            if failed is not None:
                raise failed
            if kind == "optimize":
                dropped = graph.optimize(*msg[1:])
                ids, poses = graph.all_node_poses()
                reply = {"ids": ids, "poses": poses, "iterations": graph.iterations, "last_error": graph.last_error}
            elif kind == "gnc":
                dropped = graph.gnc_prune()
                reply = {}
            elif kind == "stats":
                dropped = []
                reply = {"peak_rss_mb": peak_rss_mb()}
            else:
                raise ValueError(f"unknown request {kind!r}")
            for f in dropped:
                loops.pop(f.record["id"])
            reply["dropped"] = [(f.record["id"], f.record["reason"]) for f in dropped]
            out = ("ok", reply)
        except Exception as e:  # reported to the caller, which raises it
            if kind in ("init", "ops"):
                failed = e
                continue
            out = ("error", f"{type(e).__name__}: {e}")
        try:
            send.send(out)
        except OSError:  # the caller has gone (it stopped on an error of its own, which it reports)
            return


def _apply(pose_graph, graph, loops: dict, msg):
    """An ``init`` or ``ops`` message applied to the child's graph; returns the graph."""
    if msg[0] == "init":
        return pose_graph(*msg[1:])
    for op in msg[1]:
        if op[0] == "node":
            graph.add_node(op[1], op[2])
        elif op[0] == "intra":
            graph.add_intra(*op[1:])
        elif op[0] == "loop":
            loops[op[1]] = graph.add_loop(*op[2:6], {"id": op[1]}, heading_only=op[6])
        else:  # remove
            graph.remove_loop(loops.pop(op[1]), op[2])
    return graph


if __name__ == "__main__":
    import logging

    # the solver's warnings (``pose_graph``) reach the same stderr as the caller's, in the CLI's form
    logging.basicConfig(level=logging.WARNING, format="slam2d: %(levelname)s: %(message)s")
    _serve(Connection(int(sys.argv[1]), writable=False), Connection(int(sys.argv[2]), readable=False))
