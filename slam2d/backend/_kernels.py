"""Numba kernels of global SLAM: shortest paths for the drift bound (``drift.py``; Dijkstra 1959,
with a binary heap). Each kernel has an oracle in the tests (``tests/test_drift.py``: scipy's)."""
from __future__ import annotations

import heapq

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def shortest_distances(n, heads, tails, weights, source):
    """Length of the shortest path from ``source`` to each of the ``n`` vertices of the undirected
    graph with edges (heads[e], tails[e]) of weight weights[e] ≥ 0 (parallel edges allowed: the
    lightest counts); inf where none leads."""
    start = np.zeros(n + 1, dtype=np.int64)
    for e in range(heads.shape[0]):
        start[heads[e] + 1] += 1
        start[tails[e] + 1] += 1
    for v in range(n):
        start[v + 1] += start[v]
    fill = start[:-1].copy()
    adj = np.empty(start[n], dtype=np.int64)
    adj_w = np.empty(start[n])
    for e in range(heads.shape[0]):
        for a, b in ((heads[e], tails[e]), (tails[e], heads[e])):
            adj[fill[a]] = b
            adj_w[fill[a]] = weights[e]
            fill[a] += 1
    dist = np.full(n, np.inf)
    dist[source] = 0.0
    heap = [(0.0, np.int64(source))]
    while len(heap):
        d, u = heapq.heappop(heap)
        if d > dist[u]:
            continue
        for p in range(start[u], start[u + 1]):
            v = adj[p]
            nd = d + adj_w[p]
            if nd < dist[v]:
                dist[v] = nd
                heapq.heappush(heap, (nd, v))
    return dist
