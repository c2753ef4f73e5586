"""Pairwise consistency of loop closures through the local chain (the idea of PCM, Mangelson et
al. 2018, "Pairwise Consistent Measurement Set Maximization", here with a drift-bounded test
instead of a Mahalanobis one).

Two loop constraints (a₁ → j₁) and (a₂ → j₂) close a cycle through local SLAM:
a₁ →loop₁→ j₁ →local→ j₂ →loop₂⁻¹→ a₂ →local→ a₁, which is the identity when both loops are
true, up to local SLAM's drift along the two local legs (|path a₁…a₂| + |path j₁…j₂|). A pair is
*tested* when those legs are short (``max_chain``), and *consistent* when the cycle's error is
below ``tol_t + drift_t · chain`` metres and ``tol_r + drift_r · chain`` radians. The judge is
independent of the pose-graph solution: it uses only local SLAM poses and the loops themselves.

Loops are then removed greedily, most contradicted first, while some loop is contradicted by
more tested partners than support it, and by at least two (one contradiction between two loops
cannot say which of them is false: that is left to the residual check); with ``min_support`` > 0, a loop that has fewer consistent
partners than that is removed too (a single loop that nothing confirms).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam2d.geometry import between, compose, inverse


@dataclass
class ConsistencyParams:
    max_chain: float = 30.0   # m of local path on the two legs together
    tol_t: float = 0.3        # m
    drift_t: float = 0.03     # m per m of chain
    tol_r: float = 0.035      # rad
    drift_r: float = 0.005    # rad per m of chain (0.3°)
    min_support: int = 0


@dataclass
class PairTests:
    """The tested pairs of ``n`` loops, both ways round: loop ``src[e]`` with loop ``dst[e]``,
    ``consistent[e]`` whether their cycle closed. Untested pairs are absent: a loop is tested only
    against loops within ``max_chain`` of it, so memory and time follow the loops' neighbourhoods,
    not the square of their number."""

    n: int
    src: np.ndarray
    dst: np.ndarray
    consistent: np.ndarray

    def dense(self) -> np.ndarray:
        """(n, n) int8: +1 tested and consistent, -1 tested and inconsistent, 0 untested (incl. diagonal)."""
        out = np.zeros((self.n, self.n), dtype=np.int8)
        out[self.src, self.dst] = np.where(self.consistent, 1, -1)
        return out


def candidate_pairs(pa: np.ndarray, max_chain: float) -> tuple[np.ndarray, np.ndarray]:
    """Every pair (i < k) of loops whose anchors lie within ``max_chain`` of each other along the
    local path (``pa``), found by sorting instead of enumerating all pairs. The chain of a pair is at
    least that distance, so no pair the test can reach is missed."""
    n = len(pa)
    order = np.argsort(pa, kind="stable")
    s = pa[order]
    hi = np.searchsorted(s, s + max_chain * (1.0 + 1e-9) + 1e-9, side="right")
    count = np.maximum(hi - np.arange(n) - 1, 0)
    a = np.repeat(np.arange(n), count)
    b = a + 1 + (np.arange(len(a)) - np.repeat(np.cumsum(count) - count, count))
    i, k = order[a], order[b]
    return np.minimum(i, k), np.maximum(i, k)


def fresh_pairs(pa: np.ndarray, fresh: np.ndarray, max_chain: float) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of ``candidate_pairs`` that involve a loop marked ``fresh``, found from those loops
    alone: for each, the loops whose anchors lie within ``max_chain`` of its own along the path (a
    window of the loops sorted by path), each pair once (i < k). Its cost follows the fresh loops'
    neighbourhoods, not every pair of loops, so a cache that tests only new pairs stays cheap as the
    loops grow in number."""
    n = len(pa)
    f = np.flatnonzero(fresh)
    if n < 2 or not len(f):
        none = np.zeros(0, dtype=np.int64)
        return none, none
    order = np.argsort(pa, kind="stable")
    s = pa[order]
    reach = max_chain * (1.0 + 1e-9) + 1e-9  # as ``candidate_pairs``: no pair the test can reach is missed
    lo = np.searchsorted(s, pa[f] - reach, side="left")
    hi = np.searchsorted(s, pa[f] + reach, side="right")
    count = hi - lo
    a = np.repeat(f, count)
    b = order[np.arange(count.sum()) - np.repeat(np.cumsum(count) - count - lo, count)]
    # not with itself, and a pair of two fresh loops once (from its smaller index)
    keep = (a != b) & ~(fresh[b] & (b < a))
    i, k = a[keep], b[keep]
    return np.minimum(i, k), np.maximum(i, k)


def pair_tests(rel: np.ndarray, la: np.ndarray, lj: np.ndarray, pa: np.ndarray, pj: np.ndarray,
               p: ConsistencyParams) -> PairTests:
    """Test every pair of loops whose two local legs are short enough (module docstring).

    ``rel`` (L, 3) loop relative poses (node in anchor frame); ``la``/``lj`` (L, 3) local SLAM poses of
    the anchors / nodes; ``pa``/``pj`` (L,) their path length along the local trajectory [m]."""
    n = len(rel)
    if n < 2:
        return _both_ways(n)
    return _both_ways(n, *pair_tests_of(*candidate_pairs(pa, p.max_chain), rel, la, lj, pa, pj, p))


def _both_ways(n, i=None, k=None, ok=None) -> PairTests:
    """``PairTests`` of ``n`` loops from pairs (i, k) listed once (none: no pair)."""
    if i is None:
        none = np.zeros(0, dtype=np.int64)
        return PairTests(n, none, none, np.zeros(0, bool))
    return PairTests(n, np.concatenate([i, k]), np.concatenate([k, i]), np.concatenate([ok, ok]))


def pair_tests_of(i, k, rel, la, lj, pa, pj, p: ConsistencyParams):
    """The candidate pairs (``i``, ``k``) whose chain is short enough, and whether each cycle closed."""
    chain = np.abs(pa[i] - pa[k]) + np.abs(pj[i] - pj[k])
    tested = chain <= p.max_chain
    i, k, chain = i[tested], k[tested], chain[tested]
    e = compose(compose(compose(rel[i], between(lj[i], lj[k])), inverse(rel[k])), between(la[k], la[i]))
    ok = (np.hypot(e[:, 0], e[:, 1]) <= p.tol_t + p.drift_t * chain) & (np.abs(e[:, 2]) <= p.tol_r + p.drift_r * chain)
    return i, k, ok


class PairCache:
    """``pair_tests`` over a growing set of loops, each pair tested once: a pair's test depends only on
    its two loops (their relative poses, local poses and paths never change), so a call tests only the
    pairs that involve loops it has not seen and takes the others from earlier calls. Loops are known
    by ids that grow with every loop added; a loop no longer passed (removed) drops out of the result."""

    def __init__(self, p: ConsistencyParams):
        self.p = p
        self.seen = -1  # the largest id tested so far
        self.a = np.zeros(0, dtype=np.int64)  # tested pairs (ids), a < b
        self.b = np.zeros(0, dtype=np.int64)
        self.ok = np.zeros(0, dtype=bool)

    def tests(self, ids: np.ndarray, rel, la, lj, pa, pj) -> PairTests:
        """``pair_tests`` of the loops ``ids`` (increasing in the order they were added; arrays as there)."""
        ids = np.asarray(ids, dtype=np.int64)
        n = len(ids)
        if n < 2:
            return _both_ways(n)
        if ids[-1] > self.seen:
            i, k = fresh_pairs(pa, ids > self.seen, self.p.max_chain)
            t = pair_tests_of(i, k, rel, la, lj, pa, pj, self.p)
            self.a = np.concatenate([self.a, ids[t[0]]])
            self.b = np.concatenate([self.b, ids[t[1]]])
            self.ok = np.concatenate([self.ok, t[2]])
            self.seen = int(ids[-1])
        index = np.full(self.seen + 1, -1, dtype=np.int64)
        index[ids] = np.arange(n)
        i, k = index[self.a], index[self.b]
        live = (i >= 0) & (k >= 0)
        return _both_ways(n, i[live], k[live], self.ok[live])


def inconsistent(t: PairTests, scores: np.ndarray, min_support: int = 0) -> list[tuple[int, str]]:
    """Indices to remove, each with its reason (module docstring)."""
    n = t.n
    alive = np.ones(n, bool)
    removed = []

    def support():
        live = alive[t.dst]
        pos = np.bincount(t.src[live & t.consistent], minlength=n)
        neg = np.bincount(t.src[live & ~t.consistent], minlength=n)
        return pos, neg

    while n:
        pos, neg = support()
        excess = np.where(alive & (neg >= 2), neg - pos, -10 ** 9)
        worst = int(np.lexsort((scores, -excess))[0])  # most contradicted, then the lowest score
        if excess[worst] > 0:
            alive[worst] = False
            removed.append((worst, f"inconsistent with {neg[worst]} of {neg[worst] + pos[worst]} loops through the local chain"))
            continue
        break
    if min_support > 0 and n:
        pos, _ = support()
        for i in np.flatnonzero(alive & (pos < min_support)):
            removed.append((int(i), f"unconfirmed: {pos[i]} consistent loops through the local chain < {min_support}"))
    return removed


__all__ = ["ConsistencyParams", "PairCache", "PairTests", "candidate_pairs", "fresh_pairs", "pair_tests", "inconsistent"]
