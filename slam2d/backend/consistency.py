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


def pair_matrix(rel: np.ndarray, la: np.ndarray, lj: np.ndarray, pa: np.ndarray, pj: np.ndarray,
                p: ConsistencyParams) -> np.ndarray:
    """(L, L) int8: +1 tested and consistent, -1 tested and inconsistent, 0 untested (incl. diagonal).

    ``rel`` (L, 3) loop relative poses (node in anchor frame); ``la``/``lj`` (L, 3) local SLAM poses of
    the anchors / nodes; ``pa``/``pj`` (L,) their path length along the local trajectory [m]."""
    n = len(rel)
    out = np.zeros((n, n), dtype=np.int8)
    if n < 2:
        return out
    i, k = np.triu_indices(n, 1)
    chain = np.abs(pa[i] - pa[k]) + np.abs(pj[i] - pj[k])
    tested = chain <= p.max_chain
    i, k, chain = i[tested], k[tested], chain[tested]
    if len(i) == 0:
        return out
    e = compose(compose(compose(rel[i], between(lj[i], lj[k])), inverse(rel[k])), between(la[k], la[i]))
    ok = (np.hypot(e[:, 0], e[:, 1]) <= p.tol_t + p.drift_t * chain) & (np.abs(e[:, 2]) <= p.tol_r + p.drift_r * chain)
    v = np.where(ok, 1, -1).astype(np.int8)
    out[i, k] = v
    out[k, i] = v
    return out


def inconsistent(m: np.ndarray, scores: np.ndarray, min_support: int = 0) -> list[tuple[int, str]]:
    """Indices to remove, each with its reason (module docstring)."""
    alive = np.ones(len(m), bool)
    removed = []
    while True:
        sub = m * alive[None, :]
        pos = (sub == 1).sum(axis=1)
        neg = (sub == -1).sum(axis=1)
        excess = np.where(alive & (neg >= 2), neg - pos, -10 ** 9)
        if len(excess) == 0:
            break
        worst = int(np.lexsort((scores, -excess))[0])  # most contradicted, then the lowest score
        if excess[worst] > 0:
            alive[worst] = False
            removed.append((worst, f"inconsistent with {neg[worst]} of {neg[worst] + pos[worst]} loops through the local chain"))
            continue
        break
    if min_support > 0:
        sub = m * alive[None, :]
        pos = (sub == 1).sum(axis=1)
        for i in np.flatnonzero(alive & (pos < min_support)):
            removed.append((int(i), f"unconfirmed: {pos[i]} consistent loops through the local chain < {min_support}"))
    return removed


__all__ = ["ConsistencyParams", "pair_matrix", "inconsistent"]
