"""Pairwise consistency of loop closures through the local chain (the idea of PCM, Mangelson et
al. 2018, "Pairwise Consistent Measurement Set Maximization", here with a drift-bounded test
instead of a Mahalanobis one).

Two loop constraints (a₁ → j₁) and (a₂ → j₂) close a cycle through local SLAM:
a₁ →loop₁→ j₁ →local→ j₂ →loop₂⁻¹→ a₂ →local→ a₁, which is the identity when both loops are
true, up to local SLAM's drift along the two local legs (|path a₁…a₂| + |path j₁…j₂|). A pair is
*tested* when those legs are short (``max_chain``), and *consistent* when the cycle's error is
below ``tol_t + drift_t · chain`` metres and ``tol_r + drift_r · chain`` radians. The judge is
independent of the pose-graph solution: it uses only local SLAM poses and the loops themselves.
Where local SLAM could not vouch for a step on either leg (a recovered or forced pose, a weak
match), the step's doubt is added to the tolerance: the drift bound's budget (``drift.py``) along
the two legs replaces ``drift · chain`` when the budgets are given.

Loops are then removed greedily, most contradicted first, while some loop is contradicted by
more tested partners than support it, and by at least two (one contradiction between two loops
cannot say which of them is false: that is left to the residual check); with ``min_support`` > 0, a loop that has fewer consistent
partners than that is removed too (a single loop that nothing confirms).

A count treats a partner far along the chain, whose loose tolerance passes an error it could not
tell from drift, as much support as a near partner's contradiction. So each loop's own error is
also estimated from all its tested partners: the mean of their cycle errors (seen from its anchor),
each weighted by the inverse square of its tolerance, as the tolerances are bounds of the drift
along each chain. A wrong loop puts the same error into every cycle it closes, near or far; a right
one only its partners' errors, which the mean dilutes. A loop contradicted by at least two partners
is removed, largest first, while its mean error exceeds both the base tolerance and the mean's own
bound (the tolerances combined: 1/sqrt(sum of 1/tol²)), in translation or in rotation.

The test also *confirms* loops (``confirmed``): one that closes consistent cycles with at least
``residual_exempt_support`` of the loops left and contradicts none is exempt from the residual check
after optimization. That check judges a loop by the solution it helped make: where local SLAM's
chain between two places drifted more than the graph lets it bend, the optimizer leaves true loops
with large residuals, and removing them lets a single loose step (a weak match's) take the whole
correction. A confirmed loop's residual says that about the chain, not about the loop.
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
    loops: tuple | None = None  # (rel, la, lj, pa, pj, ba, bj) of the n loops, for ``cycles``
    p: ConsistencyParams | None = None

    def cycles(self, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(E, 3) the cycle errors of ``edges`` (indices into src/dst), each seen from its src loop's
        anchor, and (E, 2) their tolerances (m, rad): computed when asked, as only the loops under
        suspicion need them."""
        rel, la, lj, pa, pj, ba, bj = self.loops
        i, k = self.src[edges], self.dst[edges]
        return _cycle(i, k, rel, la, lj).reshape(-1, 3), _tolerance(i, k, pa, pj, ba, bj, self.p)

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
               p: ConsistencyParams, ba: np.ndarray | None = None, bj: np.ndarray | None = None) -> PairTests:
    """Test every pair of loops whose two local legs are short enough (module docstring).

    ``rel`` (L, 3) loop relative poses (node in anchor frame); ``la``/``lj`` (L, 3) local SLAM poses of
    the anchors / nodes; ``pa``/``pj`` (L,) their path length along the local trajectory [m];
    ``ba``/``bj`` (L, 2) their cumulative drift budgets (m, rad; ``DriftBound.budget``), or None for
    ``drift · path``."""
    n = len(rel)
    t = _both_ways(n) if n < 2 else _both_ways(n, *pair_tests_of(*candidate_pairs(pa, p.max_chain), rel, la, lj,
                                                                      pa, pj, p, ba, bj))
    return _with_loops(t, p, rel, la, lj, pa, pj, ba, bj)


def _with_loops(t: PairTests, p: ConsistencyParams, *loops) -> PairTests:
    """``t`` with what ``PairTests.cycles`` reads: the loops' arrays and the parameters."""
    t.loops, t.p = loops, p
    return t


def _both_ways(n, i=None, k=None, ok=None) -> PairTests:
    """``PairTests`` of ``n`` loops from pairs (i, k) listed once (none: no pair)."""
    if i is None:
        none = np.zeros(0, dtype=np.int64)
        return PairTests(n, none, none, np.zeros(0, bool))
    return PairTests(n, np.concatenate([i, k]), np.concatenate([k, i]), np.concatenate([ok, ok]))


def _cycle(i, k, rel, la, lj):
    """The error of the cycle of loops ``i`` and ``k``, seen from loop i's anchor."""
    return compose(compose(compose(rel[i], between(lj[i], lj[k])), inverse(rel[k])), between(la[k], la[i]))


def _tolerance(i, k, pa, pj, ba, bj, p: ConsistencyParams) -> np.ndarray:
    """(E, 2) what the cycles of loops ``i`` and ``k`` may be off (m, rad): the base tolerance plus
    the drift along the two legs, from the budgets when given (with the doubt of every step on
    them), else per metre of path."""
    if ba is None:
        chain = np.abs(pa[i] - pa[k]) + np.abs(pj[i] - pj[k])
        return np.c_[p.tol_t + p.drift_t * chain, p.tol_r + p.drift_r * chain].reshape(-1, 2)
    return np.array([p.tol_t, p.tol_r]) + (np.abs(ba[i] - ba[k]) + np.abs(bj[i] - bj[k])).reshape(-1, 2)


def pair_tests_of(i, k, rel, la, lj, pa, pj, p: ConsistencyParams, ba=None, bj=None):
    """The candidate pairs (``i``, ``k``) whose chain is short enough, and whether each cycle closed."""
    chain = np.abs(pa[i] - pa[k]) + np.abs(pj[i] - pj[k])
    tested = chain <= p.max_chain
    i, k = i[tested], k[tested]
    e = _cycle(i, k, rel, la, lj).reshape(-1, 3)
    tol = _tolerance(i, k, pa, pj, ba, bj, p)
    ok = (np.hypot(e[:, 0], e[:, 1]) <= tol[:, 0]) & (np.abs(e[:, 2]) <= tol[:, 1])
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

    def tests(self, ids: np.ndarray, rel, la, lj, pa, pj, ba=None, bj=None) -> PairTests:
        """``pair_tests`` of the loops ``ids`` (increasing in the order they were added; arrays as there)."""
        ids = np.asarray(ids, dtype=np.int64)
        n = len(ids)
        if n < 2:
            return _with_loops(_both_ways(n), self.p, rel, la, lj, pa, pj, ba, bj)
        if ids[-1] > self.seen:
            i, k = fresh_pairs(pa, ids > self.seen, self.p.max_chain)
            t = pair_tests_of(i, k, rel, la, lj, pa, pj, self.p, ba, bj)
            self.a = np.concatenate([self.a, ids[t[0]]])
            self.b = np.concatenate([self.b, ids[t[1]]])
            self.ok = np.concatenate([self.ok, t[2]])
            self.seen = int(ids[-1])
        index = np.full(self.seen + 1, -1, dtype=np.int64)
        index[ids] = np.arange(n)
        i, k = index[self.a], index[self.b]
        live = (i >= 0) & (k >= 0)
        return _with_loops(_both_ways(n, i[live], k[live], self.ok[live]), self.p, rel, la, lj, pa, pj, ba, bj)


def loop_errors(t: PairTests, alive: np.ndarray, which: np.ndarray | None = None) -> np.ndarray:
    """(n,) each loop's mean cycle error over its alive tested partners, as a multiple of what it
    may be (module docstring): the larger of translation and rotation; 0 without partners, and for
    the loops not in ``which`` (a mask; default all)."""
    live = alive[t.dst] & alive[t.src]
    if which is not None:
        live &= which[t.src]
    edges = np.flatnonzero(live)
    out = np.zeros(t.n)
    if not len(edges):
        return out
    src = t.src[edges]
    e, tol = t.cycles(edges)
    for cols, base, c in (([0, 1], t.p.tol_t, 0), ([2], t.p.tol_r, 1)):
        w = 1.0 / tol[:, c] ** 2
        wsum = np.bincount(src, w, minlength=t.n)
        has = wsum > 0
        mean = np.zeros((t.n, len(cols)))
        for m, col in enumerate(cols):
            mean[has, m] = np.bincount(src, w * e[:, col], minlength=t.n)[has] / wsum[has]
        bound = np.full(t.n, np.inf)
        bound[has] = np.maximum(base, 1.0 / np.sqrt(wsum[has]))
        out = np.maximum(out, np.linalg.norm(mean, axis=1) / bound)
    return out


def support(t: PairTests, alive: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per loop, how many of its tested partners still in ``alive`` close a consistent cycle with it,
    and how many an inconsistent one."""
    live = alive[t.dst]
    pos = np.bincount(t.src[live & t.consistent], minlength=t.n)
    neg = np.bincount(t.src[live & ~t.consistent], minlength=t.n)
    return pos, neg


def confirmed(t: PairTests, alive: np.ndarray, min_consistent: int) -> np.ndarray:
    """Which loops of ``alive`` close consistent cycles with at least ``min_consistent`` other loops of
    ``alive`` and an inconsistent one with none: confirmed by loops that agree through the local chain
    (``min_consistent`` 0: none is)."""
    if min_consistent <= 0:
        return np.zeros(t.n, bool)
    pos, neg = support(t, alive)
    return alive & (pos >= min_consistent) & (neg == 0)


def inconsistent(t: PairTests, scores: np.ndarray, min_support: int = 0) -> list[tuple[int, str]]:
    """Indices to remove, each with its reason (module docstring)."""
    n = t.n
    alive = np.ones(n, bool)
    removed = []
    while n:
        pos, neg = support(t, alive)
        excess = np.where(alive & (neg >= 2), neg - pos, -10 ** 9)
        worst = int(np.lexsort((scores, -excess))[0])  # most contradicted, then the lowest score
        if excess[worst] > 0:
            alive[worst] = False
            removed.append((worst, f"inconsistent with {neg[worst]} of {neg[worst] + pos[worst]} loops through the local chain"))
            continue
        suspects = alive & (neg >= 2)
        ratio = loop_errors(t, alive, suspects) if suspects.any() else np.zeros(n)
        worst = int(np.lexsort((scores, -ratio))[0])
        if ratio[worst] > 1.0:
            alive[worst] = False
            removed.append((worst, f"its cycles with {neg[worst] + pos[worst]} loops through the local chain "
                                   f"({neg[worst]} inconsistent) put it {ratio[worst]:.1f} times its tolerance off"))
            continue
        break
    if min_support > 0 and n:
        pos, _ = support(t, alive)
        for i in np.flatnonzero(alive & (pos < min_support)):
            removed.append((int(i), f"unconfirmed: {pos[i]} consistent loops through the local chain < {min_support}"))
    return removed


__all__ = ["ConsistencyParams", "PairCache", "PairTests", "candidate_pairs", "confirmed", "fresh_pairs", "pair_tests",
           "inconsistent", "loop_errors", "support"]
