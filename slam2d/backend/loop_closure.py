"""Loop-closure constraints (Hess et al. 2016, Sec. V): a node's scan is matched against a finished
submap by branch-and-bound correlative search over precomputed max-pooled grids, scored as
the mean probability under the scan's points; matches above ``min_score`` are refined below
cell size and become constraints.

Precomputation grids are built once per finished submap and kept as uint8 (probability ×
255), which bounds their memory (level d is padded by 2^d − 1 cells on the low side so that
the search is exact across the submap's borders; level 0 is the matcher's only copy of the
values); scores are reported in [0, 1].
"""
from __future__ import annotations


import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from slam2d.geometry import between
from slam2d.matching.refine import refine
from slam2d.matching.search import MatchGrid, PrecomputationStack, SearchParameters, branch_and_bound
from slam2d.range_data import voxel_filter


@dataclass
class LoopMatch:
    pose: np.ndarray      # refined pose of the node in the submap's grid frame
    relative: np.ndarray  # submap_pose⁻¹ ∘ node pose
    score: float
    seconds: float


class StackCache:
    """The precomputation stacks of the most recently searched finished submaps.

    A stack costs several bytes per cell and is needed only while nodes are matched against
    its submap, which happens in bursts (when the robot is back in that area). Keeping the
    ``size`` most recently used ones bounds memory by the area being revisited, not by the
    whole map; an evicted stack is rebuilt, identically, from the submap's uint8 grid.
    """

    def __init__(self, size: int):
        self.size = size
        self._stacks: OrderedDict[int, PrecomputationStack] = OrderedDict()
        self.builds = 0

    def get(self, matcher: "SubmapMatcher") -> PrecomputationStack:
        key = matcher.submap.index
        st = self._stacks.get(key)
        if st is not None:
            self._stacks.move_to_end(key)
            return st
        st = PrecomputationStack(matcher.grid, matcher.depth)
        self.builds += 1
        self._stacks[key] = st
        while len(self._stacks) > self.size:
            self._stacks.popitem(last=False)
        return st

    @property
    def nbytes(self) -> int:
        return sum(st.nbytes for st in self._stacks.values())


class SubmapMatcher:
    """Branch-and-bound matcher for one finished submap."""

    def __init__(self, submap, depth: int, cache: StackCache | None = None):
        g = submap.grid
        self.submap = submap
        self.depth = depth
        q = np.clip(np.round(g.prob * 255.0), 0, 255).astype(np.uint8)
        self.grid = MatchGrid(q, g.origin, g.resolution, float(round(g.unknown_probability * 255)))
        self.cache = StackCache(1) if cache is None else cache
        self.prob = MatchGrid(g.prob, g.origin, g.resolution, g.unknown_probability)
        known = np.argwhere(g.known > 0)
        self.center_local = (g.origin + (known.mean(axis=0)[::-1] + 0.5) * g.resolution) if len(known) else g.origin

    @property
    def stack(self) -> PrecomputationStack:
        return self.cache.get(self)

    @property
    def nbytes(self) -> int:
        return self.grid.values.nbytes + self.prob.values.nbytes

    def match(self, points, initial, linear_window, angular_window, min_score, refine_weights) -> LoopMatch | None:
        t0 = time.perf_counter()
        params = SearchParameters.make(linear_window, angular_window, self.grid.resolution, points)
        cells = self.grid.cells(points, initial, params.angles)
        found = branch_and_bound(self.stack, cells, params.linear_cells, min_score * 255.0)
        if found is None:
            return None
        a, dx, dy, score = found
        res = self.grid.resolution
        pose = np.array([initial[0] + dx * res, initial[1] + dy * res, initial[2] + params.angles[a]])
        pose, _ = refine(self.prob, pose, points, *refine_weights)
        return LoopMatch(pose, between(self.submap.local_pose, pose), score / 255.0, time.perf_counter() - t0)


def loop_points(hits: np.ndarray, voxel: float) -> np.ndarray:
    return voxel_filter(np.asarray(hits, dtype=float), voxel)


__all__ = ["SubmapMatcher", "LoopMatch", "loop_points"]
