"""How far the current estimates may have two nodes wrong relative to each other: the drift
bound that sizes every loop-closure search window (Olson 2009, Sec. III: the search window
covers the prediction's uncertainty; Hess et al. 2016, Sec. V-C, search around the current
estimate).

Local SLAM drifts with the distance it covers: up to ``per_metre_t`` metres and
``per_metre_r`` radians per metre (a 3σ bound of the drift model). A step local SLAM could
not vouch for adds its ``doubt`` (``frontend.LocalSlam._step_doubt``: a recovered pose the
distance to the pose it replaced, a forced one the recovery window, a scan with no match the
regular window). Each node so carries a cumulative budget along the trajectory, one in metres
and one in radians.

The pose graph links two nodes through the cheapest stretch of local SLAM between them, loop
closures being free shortcuts; but the estimates only reflect the loops that were in the
graph when it was last optimized. So after each optimization the budget distance from the
newest node to every node is found over exactly those loops (Dijkstra over the loop ends,
the stretches between them being straight runs of the budget), and a query between two
nodes takes the cheaper of the straight run between them and the way through that newest
node: an upper bound of the true graph distance, so windows err on the wide side.
"""
from __future__ import annotations

import numpy as np

from slam2d.backend._kernels import shortest_distances


class DriftBound:
    def __init__(self, per_metre_t: float, per_metre_r: float):
        self.per_metre = (float(per_metre_t), float(per_metre_r))
        self.order: dict[int, int] = {}      # node id -> position along the trajectory
        self._buf = np.zeros((64, 2))        # cumulative budgets (m, rad) in the first _n rows; grows by doubling
        self._n = 0
        self._ref = None                     # position of the newest node at the last update
        self._dist: np.ndarray | None = None  # (n_ref + 1, 2) budget distance from it to every node up to it

    def add(self, node: int, step: float, extra_t: float = 0.0, extra_r: float = 0.0) -> None:
        """Append ``node`` after a local SLAM step of ``step`` metres; ``extra_*``: what a step local
        SLAM could not trust adds (m, rad)."""
        n = self._n
        last = (float(self._buf[n - 1, 0]), float(self._buf[n - 1, 1])) if n else (0.0, 0.0)
        if n == len(self._buf):
            self._buf = np.concatenate([self._buf, np.zeros_like(self._buf)])
        self.order[node] = n
        self._buf[n] = (last[0] + self.per_metre[0] * step + extra_t, last[1] + self.per_metre[1] * step + extra_r)
        self._n = n + 1

    def budget(self) -> np.ndarray:
        """(n, 2) cumulative budgets (m, rad) of the nodes in trajectory order (a view: read, do not keep)."""
        return self._buf[:self._n]

    def update(self, loops) -> None:
        """The loops ``(anchor, node)`` the estimates now reflect (call after each optimization)."""
        if not self._n:
            return
        b = self.budget()
        ref = len(b) - 1
        ends = np.array([(self.order[a], self.order[j]) for a, j in loops], dtype=np.int64).reshape(-1, 2)
        keys = np.unique(np.concatenate([ends.ravel(), [ref]]))
        k = len(keys)
        # edges between keys: the straight runs between consecutive ones, and the loops (free)
        run_pairs = np.c_[np.arange(k - 1), np.arange(1, k)]
        loop_pairs = np.searchsorted(keys, ends)
        is_run = np.r_[np.ones(k - 1, dtype=bool), np.zeros(len(loop_pairs), dtype=bool)]
        pairs = np.ascontiguousarray(np.concatenate([run_pairs, loop_pairs]), dtype=np.int64)
        # between two consecutive keys the budget is a straight run: a node is reached from the nearer end
        at = np.arange(ref + 1)
        hi = np.clip(np.searchsorted(keys, at, side="left"), 0, k - 1)
        lo = np.clip(np.searchsorted(keys, at, side="right") - 1, 0, k - 1)
        src = int(np.searchsorted(keys, ref))
        dist = np.empty((ref + 1, 2))
        for c in range(2):
            w = np.where(is_run, b[keys[pairs[:, 1]], c] - b[keys[pairs[:, 0]], c], 0.0)
            dk = shortest_distances(k, pairs[:, 0], pairs[:, 1], w, src)
            dist[:, c] = np.minimum(dk[lo] + np.abs(b[at, c] - b[keys[lo], c]),
                                    dk[hi] + np.abs(b[keys[hi], c] - b[at, c]))
        self._ref, self._dist = ref, dist

    def between(self, a: int, j: int) -> tuple[float, float]:
        """Bound (m, rad) on the error of the estimated pose of node ``j`` relative to node ``a``."""
        b = self.budget()
        pa, pj = self.order[a], self.order[j]
        best = np.abs(b[pa] - b[pj])
        if self._dist is not None:
            ref = self._ref
            via = self._from_ref(pa, b, ref) + self._from_ref(pj, b, ref)
            best = np.minimum(best, via)
        return float(best[0]), float(best[1])

    def _from_ref(self, p: int, b: np.ndarray, ref: int) -> np.ndarray:
        if p <= ref:
            return self._dist[p]
        return b[p] - b[ref]  # after the reference node: no shortcut the estimates know of


__all__ = ["DriftBound"]
