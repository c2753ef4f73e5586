"""How far the current estimates may have two nodes wrong relative to each other: the drift
bound that sizes every loop-closure search window (Olson 2009, Sec. III: the search window
covers the prediction's uncertainty; Hess et al. 2016, Sec. V-C, search around the current
estimate).

Local SLAM drifts with the distance it covers: up to ``per_metre_t`` metres and
``per_metre_r`` radians per metre (a 3σ bound of the drift model). A step local SLAM could
not trust (a pose recovered by the wide search, one forced in from the edge of the window, a
scan with no match) may be wrong by as much as the window it came from, so such a step adds
that window to the bound. Each node so carries a cumulative budget along the trajectory,
one in metres and one in radians.

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
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

#: added to every edge weight: scipy's sparse graphs drop edges of weight zero
_EPS = 1e-12


class DriftBound:
    def __init__(self, per_metre_t: float, per_metre_r: float):
        self.per_metre = (float(per_metre_t), float(per_metre_r))
        self.order: dict[int, int] = {}      # node id -> position along the trajectory
        self._budget: list[tuple[float, float]] = []
        self._cum: np.ndarray | None = None  # (n, 2) budgets as an array, made on demand
        self._ref = None                     # position of the newest node at the last update
        self._dist: np.ndarray | None = None  # (n_ref + 1, 2) budget distance from it to every node up to it

    def add(self, node: int, step: float, extra_t: float = 0.0, extra_r: float = 0.0) -> None:
        """Append ``node`` after a local SLAM step of ``step`` metres; ``extra_*``: what a step local
        SLAM could not trust adds (m, rad)."""
        last = self._budget[-1] if self._budget else (0.0, 0.0)
        self.order[node] = len(self._budget)
        self._budget.append((last[0] + self.per_metre[0] * step + extra_t, last[1] + self.per_metre[1] * step + extra_r))
        self._cum = None

    def budget(self) -> np.ndarray:
        if self._cum is None or len(self._cum) != len(self._budget):
            self._cum = np.array(self._budget, dtype=float).reshape(-1, 2)
        return self._cum

    def update(self, loops) -> None:
        """The loops ``(anchor, node)`` the estimates now reflect (call after each optimization)."""
        if not self._budget:
            return
        b = self.budget()
        ref = len(b) - 1
        ends = np.array([(self.order[a], self.order[j]) for a, j in loops], dtype=np.int64).reshape(-1, 2)
        keys = np.unique(np.concatenate([ends.ravel(), [ref]]))
        pos = {int(p): i for i, p in enumerate(keys)}
        k = len(keys)
        dist = np.empty((ref + 1, 2))
        src = pos[ref]
        for c in range(2):
            run = np.diff(b[keys, c]) + _EPS  # straight runs between consecutive keys
            rows = np.r_[np.arange(k - 1), [pos[int(a)] for a in ends[:, 0]]]
            cols = np.r_[np.arange(1, k), [pos[int(j)] for j in ends[:, 1]]]
            w = np.r_[run, np.full(len(ends), _EPS)]
            # a sparse matrix sums repeated entries: keep only the cheapest edge between two keys
            lo_hi = np.sort(np.c_[rows, cols], axis=1)
            first = np.lexsort((w, lo_hi[:, 1], lo_hi[:, 0]))
            lo_hi, w = lo_hi[first], w[first]
            keep = np.ones(len(w), dtype=bool)
            keep[1:] = np.any(np.diff(lo_hi, axis=0) != 0, axis=1)
            g = csr_matrix((w[keep], (lo_hi[keep, 0], lo_hi[keep, 1])), shape=(k, k))
            dk = dijkstra(g, directed=False, indices=src)
            # between two consecutive keys the budget is a straight run: reach a node from the nearer end
            at = np.arange(ref + 1)
            hi = np.clip(np.searchsorted(keys, at, side="left"), 0, k - 1)
            lo = np.clip(np.searchsorted(keys, at, side="right") - 1, 0, k - 1)
            via_lo = dk[lo] + np.abs(b[at, c] - b[keys[lo], c])
            via_hi = dk[hi] + np.abs(b[keys[hi], c] - b[at, c])
            dist[:, c] = np.minimum(via_lo, via_hi)
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
