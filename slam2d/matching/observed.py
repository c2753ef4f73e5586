"""Judging poses on mapped ground only: the bias of scoring a scan against a submap that has not
seen all of it.

A correlative score (Olson 2009, Sec. III) is the mean grid value under a scan's points, and a
point on never-observed space scores nothing. Of two candidate poses, the one that moves more
points onto the mapped part of the submap scores higher, right or not: in a corridor a scan slid
back along it lays its far end onto walls already mapped, while at its true pose that end sees
new ground. Judged only on the points that every candidate puts on observed cells, that bias is
gone and the comparison is between the poses' geometry. Local SLAM asks it before a recovered
pose replaces the window's match (``frontend.py``); loop verification asks it before a match
that moves a node away from its estimate becomes a constraint (``backend/loop_closure.py``).
"""
from __future__ import annotations

import numpy as np


def observed_scores(submap_grid, match_grid, poses, points: np.ndarray) -> list[float] | None:
    """The mean ``match_grid`` value of the points that every pose of ``poses`` puts on an observed
    cell of ``submap_grid`` (a ``ProbabilityGrid`` in ``match_grid``'s frame), one figure per pose,
    in ``match_grid``'s units (its ``scale`` applied); None when no point is on observed cells at
    every pose."""
    cells = [match_grid.cells(points, p, np.zeros(1))[0] for p in poses]
    common = np.ones(len(points), dtype=bool)
    for c in cells:
        common &= submap_grid.observed_at(c)
    if not common.any():
        return None
    return [float(match_grid.values[c[common, 1], c[common, 0]].mean()) * float(match_grid.scale) for c in cells]


__all__ = ["observed_scores"]
